"""The field step's record for each way of computing a field (SPEC steps 4-9 and the baselines): arrays and attrs
as the store keeps them, so that the in-process pipeline and the Prefect tasks compute the same field."""
from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from neuralslicer.baselines.s3_config import S3Config, S3DeformConfig
from neuralslicer.cage import Cage
from neuralslicer.model.solid import Solid
from neuralslicer.scalar_field import ScalarField

if TYPE_CHECKING:  # types only: the FEA's scipy.sparse and the samples' KD-tree are not needed to read a field
    from neuralslicer.fea.samples import StressSamples
    from neuralslicer.samples import SurfaceSamples

#: what the store keeps of a step's output: its arrays and its attributes
Record = tuple[dict[str, np.ndarray], dict[str, Any]]
Progress = Callable[[int, dict], None]


class FieldRecord(NamedTuple):
    """A field as the field steps make it and the store keeps it: ``arrays`` (G, the LPD, ``history/*`` of an
    optimisation, ``weights/*`` of its networks, the method's own) and ``attrs`` (the method, objectives, steps,
    satisfaction, ...); unpacks as ``arrays, attrs``."""

    arrays: dict[str, np.ndarray]
    attrs: dict[str, Any]

    @property
    def steps(self) -> int:
        """Optimisation steps taken (0 for the height field)."""
        return int(self.attrs.get("steps", 0))


def height_record(cage: Cage) -> FieldRecord:
    """The height field G = z (no objectives: planar layers)."""
    arrays, attrs = ScalarField.height(cage.vertices, cage.tets).to_arrays()
    return FieldRecord(arrays, {**attrs, "objectives": [], "steps": 0})


def s3_record(cage: Cage, solid: Solid, samples: SurfaceSamples, stress_samples: StressSamples | None, objectives: list[str],
              config: S3DeformConfig, name: str, progress: Progress | None = None) -> FieldRecord:
    """S3-Slicer's field: its iterative deformation of the model's tet mesh (when the model is one tet mesh, else
    the cage), carried to the cage."""
    from neuralslicer.baselines.s3_deform import s3_field

    tet = next((m for m in solid.components if getattr(m, "tets", None) is not None), None)
    result = s3_field(cage.vertices, cage.tets, samples,
                      (tet.vertices, tet.tets) if tet is not None and len(solid.components) == 1 else None,
                      stress_samples, objectives, config, name, progress=progress)
    return FieldRecord(*result.to_arrays())


def s3_oneshot_record(cage: Cage, solid: Solid, samples: SurfaceSamples, stress_samples: StressSamples | None,
                      objectives: list[str], config: S3Config, progress: Progress | None = None) -> FieldRecord:
    """The one-shot S3 variant's field: per-element rotations optimised in the deformed space, one ARAP solve."""
    from neuralslicer.baselines.s3 import optimise_s3   # torch: only when a field is optimised

    result = optimise_s3(cage.vertices, cage.tets, samples, stress_samples, objectives, config, solid.platform_z,
                         progress=progress)
    arrays, attrs = result.to_arrays()
    return FieldRecord(arrays, {**attrs, "kind": "s3_oneshot", "method": "s3_oneshot",
                                "objectives": sorted(set(objectives) & {"sf", "sr"}),
                                "wall_time_s": result.wall_time_s})


def blend_record(cage: Cage, field: FieldRecord, t: float) -> FieldRecord:
    """The field blended toward planar layers, (1 - t) G + t z, keeping its optimisation history."""
    arrays, attrs = ScalarField.from_arrays(cage.vertices, cage.tets, *field).blend(t).to_arrays()
    history = {k: v for k, v in field.arrays.items() if k.startswith("history/")}
    return FieldRecord({**arrays, **history}, attrs)


def field_of(cage: Cage, record: FieldRecord) -> ScalarField:
    """The ScalarField of a field record."""
    return ScalarField.from_arrays(cage.vertices, cage.tets, *record)


def history_of(record: FieldRecord) -> dict[str, np.ndarray]:
    """The optimisation's per-step history in a field record (empty for the height field)."""
    return {k.split("/", 1)[1]: v for k, v in record.arrays.items() if k.startswith("history/")}
