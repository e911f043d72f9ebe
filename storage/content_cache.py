"""A content-addressed cache shared by every store on a machine: results of steps that are costly or not
deterministic everywhere (fTetWild's cage: seeded on Linux, neuralslicer/tetwild_seed.py, varying from call to call
elsewhere), keyed by the digest of their inputs, so the same inputs give the same artifact in any store.

Entries are ``<root>/<kind>/<key>.npz`` (arrays, read with ``allow_pickle=False``: an entry cannot run
code) beside ``<key>.json`` (attributes), each written atomically. The root is ``NEURALSLICER_CACHE_DIR``,
else ``$XDG_CACHE_HOME/neuralslicer``, else ``~/.cache/neuralslicer``; ``NEURALSLICER_CACHE_DIR=off``
turns the cache off. A cache that cannot be written is skipped, never an error.
"""
from __future__ import annotations

import json
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from neuralslicer.fileio import atomic_path, write_json_atomic

OFF = ("", "0", "off", "none", "false", "no")
_KEY = re.compile(r"^[0-9A-Za-z_.-]{1,128}$")


def cache_root(environ: Mapping[str, str] | None = None) -> Path | None:
    """The cache folder the environment names (None when the cache is off)."""
    env = os.environ if environ is None else environ
    if "NEURALSLICER_CACHE_DIR" in env:
        value = env["NEURALSLICER_CACHE_DIR"].strip()
        return None if value.lower() in OFF else Path(value).expanduser()
    base = env.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base).expanduser() / "neuralslicer"


class ContentCache:
    """Artifacts (arrays + JSON attributes) by kind and input digest, in a folder shared across stores."""

    def __init__(self, root: str | Path | None) -> None:
        """The cache in ``root`` (None: a cache that holds nothing and keeps nothing)."""
        self.root = Path(root) if root is not None else None

    def _paths(self, kind: str, key: str) -> tuple[Path, Path]:
        """(arrays file, attributes file) of one entry."""
        if self.root is None or not (_KEY.match(kind) and _KEY.match(key)):
            raise ValueError(f"invalid cache entry {kind!r}/{key!r}")
        folder = self.root / kind
        return folder / f"{key}.npz", folder / f"{key}.json"

    def load(self, kind: str, key: str) -> tuple[dict[str, np.ndarray], dict[str, Any]] | None:
        """The entry's (arrays, attrs), or None when it is absent or unreadable."""
        if self.root is None:
            return None
        arrays_file, attrs_file = self._paths(kind, key)
        try:
            attrs = json.loads(attrs_file.read_text())
            if not isinstance(attrs, dict) or attrs.get("cache_key") != key:
                return None
            with np.load(arrays_file, allow_pickle=False) as data:
                arrays = {name: data[name] for name in data.files}
        except (OSError, ValueError, KeyError):
            return None
        return arrays, attrs

    def save(self, kind: str, key: str, arrays: Mapping[str, np.ndarray], attrs: Mapping[str, Any]) -> bool:
        """Keep an entry (arrays first, then the attributes that make it visible); False when it cannot be written."""
        if self.root is None:
            return False
        arrays_file, attrs_file = self._paths(kind, key)
        try:
            with atomic_path(arrays_file) as tmp:
                with open(tmp, "wb") as fh:
                    np.savez(fh, **{k: np.asarray(v) for k, v in arrays.items()})
            write_json_atomic(attrs_file, {**attrs, "cache_key": key})
        except OSError:
            return False
        return True
