"""LinuxCNC: screw compensation files (``COMP_FILE``, ``COMP_FILE_TYPE = 0``) per joint.

From the LinuxCNC INI configuration manual, section ``[JOINT_<num>]``:

- ``COMP_FILE`` is a text file of triplets, one per line, separated by
  spaces, in machine units, in ascending order of the first value: the nominal
  (commanded) position, then two values that depend on ``COMP_FILE_TYPE``;
- type 0: the second value is the *actual* position when the joint moves in
  the positive direction, the third the actual position moving negative;
- at most 256 triplets per joint (``EMCMOT_COMP_SIZE``); with a COMP_FILE,
  BACKLASH is not used.

So LinuxCNC takes measured positions, not corrections: ``nominal + EXX+`` and
``nominal + EXX-`` (the mean table in both columns without bidirectional
data). Joints 0, 1, 2 are taken to be X, Y, Z (trivkins); the nominal
positions are machine coordinates. Only positioning errors can be written.
"""

from __future__ import annotations

from xmalign.comp.common import POSITIONING, check_count, directional, table
from xmalign.formats.error_tables import ErrorTableSet
from xmalign.rigid_body import AXES, AXIS_INDEX, Chain

NAME = "linuxcnc"
MAX_TRIPLETS = 256
COMPENSATES = frozenset(POSITIONING.values())


def render_joint(tables: ErrorTableSet, axis: str) -> str:
    """The comp file of one joint: ``nominal forward reverse`` per line, mm."""
    name = POSITIONING[axis]
    pair = directional(tables, name)
    forward, reverse = pair if pair else (table(tables, name), table(tables, name))
    check_count(len(forward.positions_mm), MAX_TRIPLETS, f"joint {AXIS_INDEX[axis]}", "LinuxCNC")
    lines = [
        f"{p:.6f} {p + f:.6f} {p + r:.6f}"
        for p, f, r in zip(forward.positions_mm, forward.values, reverse.values, strict=True)
    ]
    return "\n".join(lines) + "\n"


def render_ini() -> str:
    """The lines to add to the INI file."""
    out = ["# xmalign: add to the machine's INI file (COMP_FILE_TYPE 0: actual positions)"]
    for axis in AXES:
        out += [
            "",
            f"[JOINT_{AXIS_INDEX[axis]}]",
            f"COMP_FILE = {_file(axis)}",
            "COMP_FILE_TYPE = 0",
        ]
    return "\n".join(out) + "\n"


def _file(axis: str) -> str:
    return f"joint{AXIS_INDEX[axis]}.comp"


def render(tables: ErrorTableSet, chain: Chain) -> dict[str, str]:
    """File name -> text of the three comp files and the INI snippet."""
    files = {_file(axis): render_joint(tables, axis) for axis in AXES}
    files["joints.ini"] = render_ini()
    return files
