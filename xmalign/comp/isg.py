"""ISG kernel (Beckhoff TwinCAT CNC): volumetric compensation parameter file, ISG CSV format.

From the ISG / TF5280 "Volumetric compensation" documentation:

- a header line names the columns (arguments and parameters), the rows below
  are the records; ``//`` starts a comment line; ``#`` is a file break after
  which a new header and its records follow;
- position errors (``C0Y``, ``A0Z``, ``B0Z``, ...) are constants, one record;
  component errors (``EXX EYX EZX EAX EBX ECX``) are tabulated against their
  argument ``X`` (mm);
- parameter values are in mm for offsets and rad for angles.

The kernel builds the compensation from the ISO 230 error model itself, so the
values are errors, not corrections. They are ISO 230-1 errors of each axis's
own motion: a workpiece-side axis's tables are written with the sign reversed
(docs/conventions.md states every error as tool relative to workpiece). The chain
goes into the header comment; the start-up list (``vol_comp[i].file_name``,
axis assignment, ``Chain``, ``max_records``) is configured in the CNC.
"""

from __future__ import annotations

from xmalign.comp.common import Comment, Loading, with_history
from xmalign.comp.fit import CompensationFit, CompModel
from xmalign.machine import Machine
from xmalign.rigid_body import AXES, ROTATION_NAMES, SQUARENESS_NAMES, TRANSLATION_NAMES, Chain

NAME = "isg"
MODEL = CompModel(pairs=(), directional=False, volumetric=True)
FILE_NAME = "vol_comp.csv"
FORMAT = "xmalign.comp.isg/1"


def _number(value: float) -> str:
    return f"{value:.9g}"


def render(fit: CompensationFit, machine: Machine) -> dict[str, str]:
    """File name -> text of the volumetric parameter file (``post``'s model, direction-free)."""
    chain = Chain.parse(machine.chain)
    model = fit.mean
    squareness = [model.squareness.get(name, 0.0) for name in SQUARENESS_NAMES]
    lines = [
        f"// xmalign volumetric compensation, chain {chain}, workpiece axes:"
        f" {len(chain.workpiece)}; mm and rad; tool offset for the CNC's tool data:"
        f" {' '.join(f'{v:g}' for v in machine.cnc.tool_offset_mm)} mm",
        "// position errors",
        " ".join(name[1:] for name in SQUARENESS_NAMES),
        " ".join(_number(v) for v in squareness),
    ]
    records = 1
    for axis in AXES:
        names = (*TRANSLATION_NAMES[axis], *ROTATION_NAMES[axis])
        sign = -1.0 if axis in chain.workpiece else 1.0
        positions = model.tables[f"E{axis}{axis}"][0]
        columns = [model.value(name, positions) for name in names]
        lines += ["#", f"// component errors of {axis}", " ".join([axis, *names])]
        for n, position in enumerate(positions):
            values = [sign * column[n] for column in columns]
            lines.append(" ".join([_number(position), *(_number(v) for v in values)]))
        records += len(positions)
    lines.insert(1, f"// records: {records} (vol_comp[i].max_records must be at least this)")
    lines[2:2] = loading(fit, machine).lines("// ")
    files = {FILE_NAME: "\n".join(lines) + "\n"}
    return with_history(files, FORMAT, fit.sources, {FILE_NAME: Comment("// ", skip=1)})


def loading(fit: CompensationFit, machine: Machine) -> Loading:
    """Reversal, the check on the machine and what the documentation left open."""
    return Loading(
        reversal=(
            "the volumetric model is direction-free: keep the control's backlash compensation"
            " as it was during the measurement"
        ),
        check=(
            "with vol_comp active, move to the two opposite corners of the travel and compare"
            " the positions with the verification run (xmalign post --verify-data)"
        ),
        unconfirmed=("a complete published parameter file (only the format page's example)",),
        warnings=fit.warnings,
    )
