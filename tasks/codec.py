"""The store codec: how each step's artifact is read back (and the print encoded), in one place."""
from __future__ import annotations

import hashlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

from neuralslicer.cage import Cage
from neuralslicer.fea.samples import StressSamples
from neuralslicer.layers import Layers
from neuralslicer.model.solid import Model, Solid
from neuralslicer.motion.collision import CollisionMap, part_collisions
from neuralslicer.motion.planning import MachineProgram, ProgramMoves, program_header
from neuralslicer.run.field_step import FieldRecord, history_of
from neuralslicer.run.pipeline import RoundPrint, TriedPrint
from neuralslicer.samples import SurfaceSamples
from neuralslicer.scalar_field import ScalarField
from neuralslicer.toolpath.types import Toolpaths
from neuralslicer.storage import ArtifactRef, ArtifactStore, digest
from neuralslicer.storage.layout import group_kind
from neuralslicer.tasks.release import HIT_XYZ, released, released_map, whole

P = TypeVar("P", bound=ProgramMoves)

if TYPE_CHECKING:  # the output contract (and the report's plotting libraries) only when a run is exported
    import trimesh

    from neuralslicer.fea.solver import FEAResult, PrintedFEA
    from neuralslicer.run.outputs import RunResults, StrengthRound


def read(ref: ArtifactRef, names: list[str] | None = None) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Arrays (all, or the named ones) and attributes of a stored step."""
    return ArtifactStore(ref.store, create=False).read(ref.path, names)


def attrs_of(ref: ArtifactRef) -> dict[str, Any]:
    """Attributes of a stored step."""
    return ArtifactStore(ref.store, create=False).attrs(ref.path)


def step_attrs(refs: dict[str, ArtifactRef | None]) -> dict[str, dict[str, Any]]:
    """Attributes of each stored step (wall times, reports), the missing ones left out."""
    return {k: attrs_of(r) for k, r in refs.items() if r is not None}


def read_solid(ref: ArtifactRef) -> Solid:
    """The implicit solid stored by the model step."""
    return Solid.from_arrays(*read(ref))


def read_surface(ref: ArtifactRef) -> tuple[trimesh.Trimesh, dict[str, Any]]:
    """The boundary surface stored by the surface step, with its genus, volume and bounds."""
    import trimesh

    arrays, attrs = read(ref)
    return trimesh.Trimesh(arrays["vertices"], arrays["faces"], process=False), attrs


def read_samples(ref: ArtifactRef) -> SurfaceSamples:
    """Surface samples B."""
    return SurfaceSamples.from_arrays(*read(ref))


def read_stress_samples(ref: ArtifactRef) -> StressSamples:
    """Stress samples T."""
    return StressSamples.from_arrays(*read(ref))


def read_cage(ref: ArtifactRef) -> Cage:
    """The cage."""
    return Cage.from_arrays(*read(ref))


def read_field(cage: Cage, ref: ArtifactRef) -> ScalarField:
    """The printing field G on its cage."""
    arrays, attrs = read(ref, ["G"])
    return ScalarField.from_arrays(cage.vertices, cage.tets, arrays, attrs)


def read_field_history(ref: ArtifactRef) -> dict[str, np.ndarray]:
    """The optimisation's per-step history of a stored field (empty for the height field)."""
    return history_of(FieldRecord(*read(ref)))


def read_layers(ref: ArtifactRef) -> Layers:
    """Layers in print order."""
    return Layers.from_arrays(*read(ref))


def read_machine_program(ref: ArtifactRef) -> MachineProgram:
    """The machine program of a stored print alone (not its toolpaths or collisions)."""
    store = ArtifactStore(ref.store, create=False)
    arrays, attrs = store.read(whole(ref).path, [f"program/{k}" for k in MachineProgram.ARRAYS])
    return MachineProgram.from_arrays({k.split("/", 1)[1]: v for k, v in arrays.items()}, attrs["program"])


def read_toolpaths(ref: ArtifactRef) -> Toolpaths:
    """The toolpaths step's waypoints."""
    return Toolpaths.from_arrays(*read(whole(ref)))


#: bytes of G-code read from the store at a time
GCODE_CHUNK_BYTES = 16 << 20


@dataclass(frozen=True)
class StoredBytes:
    """Bytes kept in the store (a uint8 array), read in chunks each time they are iterated: a 600 MB program
    is written out without ever being whole in memory."""

    ref: ArtifactRef
    name: str
    chunk_bytes: int = GCODE_CHUNK_BYTES

    def __iter__(self) -> Iterator[bytes]:
        """The bytes, a chunk at a time."""
        for part in ArtifactStore(self.ref.store, create=False).read_slices(self.ref.path, self.name, self.chunk_bytes):
            yield part.tobytes()


def read_program(ref: ArtifactRef) -> StoredBytes:
    """The program step's G-code, read a chunk at a time when iterated."""
    return StoredBytes(ref, "gcode")


def read_motion(ref: ArtifactRef, program: type[P] = MachineProgram, toolpaths: bool = True
                ) -> tuple[Toolpaths | None, P, dict]:
    """Toolpaths, machine program and print metrics (the inverse of ``Motion.to_arrays``); ``program``: ProgramMoves to
    read only the program's arrays that drawing it needs; without ``toolpaths`` the toolpaths are not read (None)."""
    names = ([f"toolpaths/{k}" for k in Toolpaths.ARRAYS] if toolpaths else []) + [f"program/{k}" for k in program.ARRAYS]
    arrays, attrs = ArtifactStore(ref.store, create=False).read(whole(ref).path, names)
    part = {p: {k.split("/", 1)[1]: v for k, v in arrays.items() if k.startswith(p + "/")} for p in ("toolpaths", "program")}
    return (
        Toolpaths.from_arrays(part["toolpaths"], attrs["toolpaths"]) if toolpaths else None,
        program.from_arrays(part["program"], attrs["program"]),
        attrs["metrics"],
    )


class StoredToolpaths(Toolpaths):
    """A stored print's toolpaths (the motion step's, as moved): their attrs read at once, their columns all read when
    one is first used, in the process that uses it; ``column`` reads one alone and ``blocks`` a block of rows at a
    time, without the others, until then. The export draws the preview and writes the CSV of a large print so."""

    def __init__(self, ref: ArtifactRef) -> None:  # noqa: D107 - the dataclass's fields come from the store
        self.ref = whole(ref)
        self.attrs = Toolpaths.stored_attrs(attrs_of(ref)["toolpaths"])

    def __getattr__(self, name: str) -> Any:
        """A column: every column read from the store on the first use of one."""
        if name not in Toolpaths.ARRAYS:
            raise AttributeError(name)
        return getattr(self.load(), name)

    def load(self) -> Toolpaths:
        """These toolpaths with every column read from the store (once)."""
        if not self.loaded:
            arrays, _ = read(self.ref, [f"toolpaths/{k}" for k in Toolpaths.ARRAYS])
            for k in Toolpaths.ARRAYS:
                setattr(self, k, Toolpaths.stored_column(k, arrays[f"toolpaths/{k}"]))
        return self

    @property
    def loaded(self) -> bool:
        """Whether the columns have been read."""
        return "xyz" in vars(self)

    def column(self, name: str) -> np.ndarray:
        """One column, read alone from the store unless all are in memory."""
        if self.loaded:
            return getattr(self, name)
        return Toolpaths.stored_column(name, read(self.ref, [f"toolpaths/{name}"])[0][f"toolpaths/{name}"])

    def blocks(self, rows: int) -> Iterator[Toolpaths]:
        """The waypoints ``rows`` at a time, read from the store a block at a time unless all are in memory."""
        if self.loaded:
            yield from super().blocks(rows)
            return
        store = ArtifactStore(self.ref.store, create=False)
        columns = [store.read_slices(self.ref.path, f"toolpaths/{k}", rows) for k in Toolpaths.ARRAYS]
        for parts in zip(*columns):
            yield Toolpaths.from_arrays(dict(zip(Toolpaths.ARRAYS, parts)))


class StoredProgram:
    """A stored print's machine program as the export uses it: its profile, part offset and attributes read at once,
    its moves (:class:`ProgramMoves`, some 80 bytes a waypoint) read from the store only by ``read()``: the preview,
    the one job that draws them, holds them for its own time, not the whole export's."""

    def __init__(self, ref: ArtifactRef) -> None:
        """The program of the print stored as the group of ``ref``."""
        self.ref = whole(ref)
        self.profile, self.part_offset, self.attrs = program_header(attrs_of(ref)["program"])

    def read(self) -> ProgramMoves:
        """The program's moves, read from the store."""
        return read_motion(self.ref, ProgramMoves, toolpaths=False)[1]


def read_collision_map(ref: ArtifactRef) -> CollisionMap:
    """Where the head of a stored print hits, as its figure draws it (its waypoints read and dropped again; a
    released print's map as it kept it)."""
    if released(ref):
        return released_map(ref)
    arrays, _ = read(ref, ["toolpaths/xyz", "collisions/indices"])
    return CollisionMap.of_indices(arrays["toolpaths/xyz"], arrays["collisions/indices"])


def read_collided(ref: ArtifactRef) -> np.ndarray:
    """Toolpath waypoint indices (c,) whose head collides in a stored print (``CollisionReport.indices``)."""
    return np.asarray(read(ref, ["collisions/indices"])[0]["collisions/indices"], np.int64)


def read_part_collisions(ref: ArtifactRef) -> tuple[np.ndarray, np.ndarray]:
    """(hits (k,3), witnesses (k,3)) of a stored print (:func:`part_collisions`; NaN witnesses where the print
    predates stored locations; a released print's from the colliding waypoints it kept)."""
    kept = released(ref)   # a released print keeps the colliding waypoints alone, in the order of the indices
    xyz = HIT_XYZ if kept else "toolpaths/xyz"
    names = [xyz, "collisions/indices", "collisions/kind"]
    try:
        arrays, _ = read(ref, [*names, "collisions/locations"])
    except KeyError:
        arrays, _ = read(ref, names)
    indices = np.arange(len(arrays[xyz])) if kept else arrays["collisions/indices"]
    return part_collisions(arrays[xyz], indices, arrays["collisions/kind"], arrays.get("collisions/locations"))


class StoredMotion:
    """A stored print (the motion step's group) read like :class:`neuralslicer.motion.output.Motion`: each part a step
    uses (toolpaths, program, metrics, where the head hit) read from the store when first used, so a step that needs
    one part does not hold the others."""

    def __init__(self, ref: ArtifactRef) -> None:
        """The print stored as the group of ``ref``."""
        self.ref = ref

    @cached_property
    def toolpaths(self) -> Toolpaths:
        """The toolpaths as moved."""
        names = [f"toolpaths/{k}" for k in Toolpaths.ARRAYS]
        arrays, attrs = read(whole(self.ref), names)
        return Toolpaths.from_arrays({k.split("/", 1)[1]: v for k, v in arrays.items()}, attrs["toolpaths"])

    @cached_property
    def program(self) -> MachineProgram:
        """The machine program."""
        return read_machine_program(self.ref)

    @cached_property
    def metrics(self) -> dict[str, Any]:
        """The print's metrics."""
        return attrs_of(self.ref)["metrics"]

    def part_collisions(self) -> tuple[np.ndarray, np.ndarray]:
        """(hits (k,3), witnesses (k,3)) of the print (:func:`read_part_collisions`)."""
        return read_part_collisions(self.ref)


def read_model(ref: ArtifactRef) -> Model:
    """The model step's output: the spec, its implicit solid and the model's name."""
    return Model.from_arrays(*read(ref), name=ref.model)


def read_field_record(ref: ArtifactRef) -> FieldRecord:
    """A stored field as its step made it (every method's)."""
    return FieldRecord(*read(ref))


def read_printed_fea(ref: ArtifactRef) -> PrintedFEA:
    """The FEA of a printed part, with its strain figures and how tau_max turned."""
    from neuralslicer.fea.solver import PrintedFEA   # scipy.sparse: only where an FEA is read

    return PrintedFEA.from_arrays(*read(ref))


def read_user_points(ref: ArtifactRef) -> tuple[np.ndarray, np.ndarray]:
    """A stored user field as (points (p,3), values (p,))."""
    arrays, _ = read(ref)
    return arrays["points"], arrays["values"]


def read_fea(ref: ArtifactRef) -> FEAResult:
    """The isotropic FEA result."""
    from neuralslicer.fea.solver import FEAResult   # scipy.sparse: only where an FEA is read

    return FEAResult.from_arrays(*read(ref))


def store_user_field(store: str, model: str, path: str) -> ArtifactRef:
    """Put a user field file (.npz: points (p,3) in the build frame, values (p,)) in the store, keyed by content."""
    from neuralslicer.neural.initial_guess import load_user_field   # scipy.interpolate: only with a user field

    points, values = load_user_field(path)
    key = digest("user_field", hashlib.sha256(points.tobytes() + values.tobytes()).hexdigest())
    st = ArtifactStore(store)
    ref = st.ref(f"{model}/user_field/{key}", key)
    st.write_once(ref.path, lambda: ({"points": points, "values": values}, {"source": str(path)}))
    return ref


def read_run(model: ArtifactRef, surface: ArtifactRef, samples: ArtifactRef, cage: ArtifactRef, field: ArtifactRef,
             layers: ArtifactRef, motion: ArtifactRef, stress_samples: ArtifactRef | None, verify: ArtifactRef | None,
             attempts: list[TriedPrint[ArtifactRef]],
             sr_rounds: list[RoundPrint[ArtifactRef]] | None = None,
             toolpaths: ArtifactRef | None = None, program_ref: ArtifactRef | None = None) -> RunResults:
    """Every step's result of one slice, as the output contract needs them."""
    from neuralslicer.run.outputs import Attempt, RunResults

    refs = {"model": model, "surface": surface, "samples": samples, "cage": cage, "field": field, "layers": layers,
            "toolpaths": toolpaths, "motion": motion, "program": program_ref, "stress_samples": stress_samples,
            "verify": verify}
    c = read_cage(cage)
    surface_mesh, surface_attrs = read_surface(surface)
    # the G-code comes from the store: of the program, the export reads what it draws
    # the first print's map first: its waypoints are read and dropped before the printed print's arrays come
    first = ({f"first print ({attempts[0].label})": read_collision_map(attempts[0].motion)}
             if attempts and attempts[0].motion != motion else {})
    if program_ref is not None:   # the G-code is the program step's: the moves and waypoints read where drawn
        tp, program, print_metrics = StoredToolpaths(motion), StoredProgram(motion), attrs_of(motion)["metrics"]
    else:
        tp, program, print_metrics = read_motion(motion)
    gcode = read_program(program_ref) if program_ref is not None else None
    collided = read_collided(motion)
    maps = {**first, "printed": read_collision_map(motion)}
    return RunResults(
        model=model.model, surface=surface_mesh, surface_attrs=surface_attrs, samples=read_samples(samples), cage=c,
        cage_attrs=attrs_of(cage), field=read_field(c, field), field_history=read_field_history(field),
        layers=read_layers(layers), toolpaths=tp, program=program, print_metrics=print_metrics,
        collision_maps=maps, collided=collided, wall_s={k: a["wall_s"] for k, a in step_attrs(refs).items()},
        stress_samples=read_stress_samples(stress_samples) if stress_samples is not None else None,
        verify=read(verify) if verify is not None else None,
        attempts=[Attempt(a.label, read_field(c, a.field), attrs_of(a.motion)["metrics"]) for a in attempts],
        strength_rounds=[read_strength_round(r.label, r.motion, r.printed_fea) for r in sr_rounds or []],
        gcode=gcode,
    )


def read_strength_round(label: str, motion: ArtifactRef, printed: ArtifactRef) -> StrengthRound:
    """One strength round: its print's collisions, the FEA of that print (strain figures) and how tau_max turned."""
    from neuralslicer.run.outputs import TURN_ARRAYS, StrengthRound

    arrays, attrs = read(printed, [f"turn/{k}" for k in TURN_ARRAYS])
    return StrengthRound(label, int(attrs_of(motion)["metrics"].get("n_collisions", 0)), attrs,
                         {k.split("/", 1)[1]: np.asarray(v) for k, v in arrays.items()})


#: how an input of each kind of group is read for a step's core call (``tasks/steps.py``)
DECODERS: dict[str, Callable[[ArtifactRef], Any]] = {
    "model": read_model, "surface": read_surface, "samples": read_samples, "cage": read_cage, "fea": read_fea,
    "fea_printed": read_printed_fea, "stress_samples": read_stress_samples, "field": read_field_record,
    "field_s3": read_field_record, "field_s3_oneshot": read_field_record, "field_blend": read_field_record,
    "layers": read_layers, "toolpaths": read_toolpaths, "motion": StoredMotion, "verify": read,
    "user_field": read_user_points,
}


def decode(ref: ArtifactRef) -> Any:
    """A stored step's output as its core function returned it (or as a later step reads it: a print part by part)."""
    kind = group_kind(ref.path)
    if kind not in DECODERS:
        raise ValueError(f"{ref.path}: no step reads a group of kind {kind!r}")
    return DECODERS[kind](ref)
