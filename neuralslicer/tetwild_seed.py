"""fTetWild with a seed: the same surface, options and seed give the same tet mesh on any machine, in any process.

fTetWild varies in two ways, neither of them its threads (the mesh is the same on 1, 2 or 8). ``sort_input_faces``
(TriangleInsertion.cpp) shuffles the input triangles with a ``std::mt19937`` seeded by ``std::random_device``, a
fresh draw per call. And its generators that start from fixed seeds (``Random::next``'s ``mt19937 gen(42)``, a
``mt19937_64`` in the library) carry their state from one call to the next, so the n-th mesh of a process depends on
the meshes before it. pytetwild 0.4 exposes neither a seed nor fTetWild's ``not_sort_input``.

So each mesh is made in a fresh Python process (every generator at its start), where the extension's one global
offset table slot for libstdc++'s ``random_device::_M_getval`` (found in its ELF relocations; x86-64 and aarch64
Linux) points at libc's ``rand``, seeded by ``srand`` from the seed. Where the slot cannot be patched (another
platform, another build) :func:`tetrahedralize` says so and fTetWild draws its own seed.
"""
from __future__ import annotations

import ctypes
import json
import mmap
import os
import struct
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from neuralslicer.errors import NeuralSlicerError

GETVAL = b"_ZNSt13random_device9_M_getvalEv"  # std::random_device::_M_getval(), behind random_device::operator()
# ELF machine -> (GLOB_DAT, JUMP_SLOT): the relocation types that fill a GOT slot with a symbol's address
_GOT_RELOCATIONS = {62: (6, 7), 183: (1025, 1026)}  # EM_X86_64, EM_AARCH64
_RTLD_DI_LINKMAP = 2
_PROT_READ_WRITE = 0x1 | 0x2
_PACKAGE_ROOT = str(Path(__file__).resolve().parents[1])


def got_slots(path: str | Path, symbol: bytes = GETVAL) -> list[int]:
    """Offsets (from the load address) of the GOT slots a 64-bit little-endian ELF shared library fills with
    ``symbol``'s address; empty for another format or a library that does not import the symbol."""
    data = Path(path).read_bytes()
    if data[:6] != b"\x7fELF\x02\x01":
        return []
    machine = struct.unpack_from("<H", data, 0x12)[0]
    if machine not in _GOT_RELOCATIONS:
        return []
    shoff = struct.unpack_from("<Q", data, 0x28)[0]
    shentsize, shnum = struct.unpack_from("<HH", data, 0x3A)
    # (sh_name, sh_type, sh_flags, sh_addr, sh_offset, sh_size, sh_link, sh_info, sh_addralign, sh_entsize)
    sections = [struct.unpack_from("<IIQQQQIIQQ", data, shoff + i * shentsize) for i in range(shnum)]
    slots = []
    for section in sections:
        if section[1] != 4:  # SHT_RELA
            continue
        symtab = sections[section[6]]
        strtab = sections[symtab[6]]
        for at in range(section[4], section[4] + section[5], 24):
            r_offset, r_info = struct.unpack_from("<QQ", data, at)
            if r_info & 0xFFFFFFFF not in _GOT_RELOCATIONS[machine] or (r_info >> 32) == 0:
                continue
            name_at = strtab[4] + struct.unpack_from("<I", data, symtab[4] + (r_info >> 32) * 24)[0]
            if data[name_at:data.index(b"\0", name_at)] == symbol:
                slots.append(r_offset)
    return slots


def _load_address(library: ctypes.CDLL, libc: ctypes.CDLL) -> int:
    """Where the dynamic loader mapped ``library`` (``l_addr`` of its link map)."""
    dlinfo = getattr(libc, "dlinfo", None) or ctypes.CDLL("libdl.so.2").dlinfo
    dlinfo.argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.c_void_p]
    link_map = ctypes.c_void_p()
    if dlinfo(ctypes.c_void_p(library._handle), _RTLD_DI_LINKMAP, ctypes.byref(link_map)) != 0:
        raise OSError("dlinfo failed")
    return ctypes.c_size_t.from_address(link_map.value).value


def seed_draws(seed: int) -> bool:
    """In this process, make the loaded pytetwild extension's ``random_device`` draws libc's ``rand`` seeded from
    ``seed``; False where that cannot be done."""
    from pytetwild import PyfTetWildWrapper

    if not sys.platform.startswith("linux"):
        return False
    try:
        slots = got_slots(PyfTetWildWrapper.__file__)
        if not slots:
            return False
        libc = ctypes.CDLL(None)
        base = _load_address(ctypes.CDLL(PyfTetWildWrapper.__file__), libc)  # the loaded one (dlopen counts twice)
        rand = ctypes.cast(libc.rand, ctypes.c_void_p).value
        libc.mprotect.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
        for slot in slots:
            address = base + slot
            page = address & ~(mmap.PAGESIZE - 1)
            if libc.mprotect(page, address + 8 - page, _PROT_READ_WRITE) != 0:
                return False
            ctypes.c_void_p.from_address(address).value = rand
    except (OSError, AttributeError, ValueError, struct.error):
        return False
    libc.srand(ctypes.c_uint(seed % 0xFFFFFFFF + 1))  # glibc's srand(0) is srand(1)
    return True


def tetrahedralize(vertices: np.ndarray, faces: np.ndarray, seed: int, **options: Any
                   ) -> tuple[np.ndarray, np.ndarray, bool]:
    """``pytetwild.tetrahedralize(vertices, faces, **options)`` in a fresh process, its random draw from ``seed``.

    Returns
    -------
    vertices : (n, 3) float64
    tets : (m, 4) int32
    seeded : bool
        False where the draw could not be seeded (fTetWild then draws its own, and the mesh varies by call).
    """
    with tempfile.TemporaryDirectory(prefix="neuralslicer-tetwild-") as tmp:  # fTetWild leaves a debug file in cwd
        folder = Path(tmp)
        np.savez(folder / "surface.npz", vertices=np.asarray(vertices, dtype=np.float64),
                 faces=np.asarray(faces, dtype=np.int32))
        (folder / "options.json").write_text(json.dumps({"seed": int(seed), "options": options}))
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [_PACKAGE_ROOT, os.environ.get("PYTHONPATH")]))}
        done = subprocess.run([sys.executable, "-m", "neuralslicer.tetwild_seed", str(folder)], cwd=folder, env=env,
                              capture_output=True, text=True)
        if done.returncode != 0:
            raise NeuralSlicerError(f"cage: fTetWild failed (exit {done.returncode}): {done.stderr.strip()[-2000:]}")
        with np.load(folder / "mesh.npz", allow_pickle=False) as mesh:
            return mesh["vertices"], mesh["tets"], bool(mesh["seeded"])


def _main(folder: Path) -> None:
    """The worker: ``surface.npz`` and ``options.json`` in ``folder`` to ``mesh.npz``."""
    import types

    # pytetwild's package imports pyvista only to give PolyData a ``.tetwild`` accessor: not needed here (0.6 s a call)
    sys.modules.setdefault("pytetwild._accessor", types.ModuleType("pytetwild._accessor"))
    import pytetwild

    request = json.loads((folder / "options.json").read_text())
    seeded = seed_draws(request["seed"])
    with np.load(folder / "surface.npz", allow_pickle=False) as surface:
        v, t = pytetwild.tetrahedralize(surface["vertices"], surface["faces"], **request["options"])
    np.savez(folder / "mesh.npz", vertices=v, tets=t, seeded=np.bool_(seeded))


if __name__ == "__main__":
    _main(Path(sys.argv[1]))
