"""`neuralslicer machines`: the shipped machine profiles, one a line, with their layouts in words."""
from __future__ import annotations

from argparse import Namespace
from typing import Any


def machine_lines(verbose: bool = False) -> list[str]:
    """``name  layout  dialect: description (nozzle)`` of every shipped profile (with ``verbose``, its kinematic
    values too)."""
    from neuralslicer.motion.profile import load_profile, profile_names

    profiles = [load_profile(name) for name in profile_names()]
    width = max((len(p.name) for p in profiles), default=0)
    layout = max((len(p.layout_words()) for p in profiles), default=0)
    lines = []
    for p in profiles:
        k = p.kinematics
        tcp = ", TCP" if k.tcp else ""
        lines.append(f"{p.name:<{width}}  {p.layout_words():<{layout}}  {p.gcode.dialect}{tcp}: {p.description} "
                     f"({p.nozzle.in_words()})")
        if verbose:
            lines.append(f"{'':<{width}}  pivot {list(k.pivot)}, c_offset {list(k.c_offset)}, tool_length "
                         f"{k.tool_length:g}, tilt {k.tilt_min_deg:g}..{k.tilt_max_deg:g} deg, nozzle cone "
                         f"{p.nozzle.cone_half_angle_deg:g} deg")
    return lines


def cmd_machines(args: Namespace) -> int:
    """List the shipped machine profiles."""
    print("\n".join(machine_lines(args.verbose)))
    print("use one with --machine NAME, or copy neuralslicer/machines/NAME.yaml, measure your machine's offsets "
          "(the file's comments say how) and pass --machine your.yaml")
    return 0


def add_machines_parser(sub: Any) -> None:
    """Options of `neuralslicer machines`."""
    p = sub.add_parser("machines", help="list the shipped machine profiles with their layouts")
    p.add_argument("-v", "--verbose", action="store_true", help="show each profile's kinematic values")
    p.set_defaults(func=cmd_machines)
