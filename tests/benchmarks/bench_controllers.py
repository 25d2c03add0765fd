"""Benchmark: the residual over the whole travel after each controller's own tables.

Run: ``PYTHONPATH=$PWD python tests/benchmarks/bench_controllers.py``

Held-out virtual machines (FYXZ and XFYZ, seeds used nowhere else) are measured
on six lines (2 bidirectional runs, setup disturbances, channel noise) and
``post`` fits the 21 error tables. For every controller xmalign writes, the
tables ``xmalign comp`` fits to that controller's model (xmalign/comp/fit.py)
are applied to the true machine, and the tool point's error left over the whole
travel (8 x 8 x 8 grid, t = [0, 0, -100] mm, a rigid motion removed, mean of
both directions) is printed next to:

- the best that controller's model allows: the same tables (nodes, reference
  point) fitted by the same code (``fit_tables``) to the *true* error field of
  the virtual machine instead of the one ``post`` predicts;
- Fanuc with its straightness compensation option loaded too (``STRAIGHTNESS.TXT``);
- per controller family and series, what the *files* make the control take out,
  read back as each family's manual says it reads them (tests/xmalign/comp/controls.py:
  Sinumerik 840D sl and 828D, Fanuc 0i and 30i, Heidenhain TNC 640 and TNC 4xx,
  LinuxCNC), both directions averaged: this sees the families' own limits (rounding
  to the detection unit, the TNC 4xx's power-of-two spacing, the 828D's eight tables);
- the full 21-error model ``post`` fitted, applied ideally;
- no compensation.

The best is fitted to the truth itself, not to the simulator's truth tables
(``truth.csv``): those set every angular error to zero at the axis's first
point, the table convention, and a constant tilt of an axis times a lever arm
that moves with other axes is no rigid motion; read back, they miss the
machine by 1.9-3.9 um here (0.07-0.09 um with the tilts kept). ``post``'s own
tables carry the same zero but move the tilts' effect into the squareness.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_linuxcnc_volumetric import TOOL_OFFSET_MM, fitted_tables, held_out_machine  # noqa: E402

from sim.machine import VirtualMachine  # noqa: E402
from tests.xmalign.comp.controls import taken_out  # noqa: E402
from xmalign.comp import WRITERS, compensate, writer  # noqa: E402
from xmalign.comp.fit import CompModel, fit_tables, travel_grid  # noqa: E402
from xmalign.formats.error_tables import ErrorTableSet  # noqa: E402
from xmalign.machine import Machine  # noqa: E402
from xmalign.post.compare import grid_points, remove_rigid_motion  # noqa: E402
from xmalign.rigid_body import AXES, Chain, ErrorModel, ErrorTables, deviation  # noqa: E402

MACHINES = (("FYXZ", 9101), ("FYXZ", 9202), ("XFYZ", 9303))
CONTROLLERS = tuple(name for name in WRITERS if name != "linuxcnc-volumetric")
#: (controller, series) whose files are read back as the control reads them
FAMILIES = (
    ("sinumerik", "840D sl"),
    ("sinumerik", "828D"),
    ("fanuc", "0i"),
    ("fanuc", "30i"),
    ("heidenhain", "TNC 640"),
    ("heidenhain", "TNC 4xx"),
    ("linuxcnc", "2.9"),
)


def left_um(
    chain: Chain, truth: ErrorModel, applied: ErrorModel | None, points: np.ndarray
) -> float:
    """RMS length of the tool point's error after ``applied`` is taken off, um."""
    error, _ = deviation(chain, points, TOOL_OFFSET_MM, truth)
    if applied is not None:
        error = error - deviation(chain, points, TOOL_OFFSET_MM, applied)[0]
    left = remove_rigid_motion(points, error)
    return float(np.sqrt(np.mean(np.sum(left**2, axis=1)))) * 1e3


def controller_model(machine: Machine, tables: ErrorTableSet, controller: str) -> ErrorModel:
    return compensate(machine, tables, controller).fit.mean


def with_option(machine: Machine, tables: ErrorTableSet, controller: str) -> ErrorModel | None:
    """The controller's tables and its option's (Fanuc straightness) together, or None."""
    fit = compensate(machine, tables, controller).fit
    if fit.optional is None:
        return None
    return ErrorTables(tables={**fit.mean.tables, **fit.optional.tables})


def read_back(machine: Machine, tables: ErrorTableSet, controller: str, series: str) -> ErrorModel:
    """What the controller of ``series`` takes out, read from the files (both directions'
    mean: the virtual machine's truth is direction-free here)."""
    family = machine.model_copy(update={"controller": controller})
    family = family.model_copy(update={"cnc": family.cnc.model_copy(update={"series": series})})
    files = compensate(family, tables, controller).files
    forward, reverse = (taken_out(controller, files, family, d) for d in "+-")
    mean = {
        name: (positions, (values + np.interp(positions, *reverse[name])) / 2)
        for name, (positions, values) in forward.items()
    }
    return ErrorTables(tables=mean)


def best_model(
    machine: Machine,
    tables: ErrorTableSet,
    controller: str,
    truth: VirtualMachine,
    option: bool = False,
) -> ErrorModel:
    """The controller's tables (with its option) on our nodes, fitted to the true field."""
    model = writer(controller).MODEL
    if model.volumetric:
        return truth
    if option:
        model = CompModel(model.pairs + model.optional, directional=False)
    nodes = {axis: tables.positioning_table(axis).positions_mm for axis in AXES}
    points = travel_grid(nodes, machine.travel_min_mm, machine.travel_max_mm)
    chain = Chain.parse(machine.chain)
    tool = machine.cnc.tool_offset
    best, converged = fit_tables(model, nodes, chain, points, tool, machine.cnc.reference, truth)
    assert converged, controller
    return best


def main() -> None:
    print(
        "residual over the whole travel, um RMS (rigid motion removed, t = [0, 0, -100] mm):"
        " after each controller's tables (best its model allows), the full model, none"
    )
    options = [name for name in CONTROLLERS if writer(name).MODEL.optional]
    columns = [*CONTROLLERS, *(f"{name} + option" for name in options)]
    print(f"| machine | {' | '.join(columns)} | full model | none |")
    print("|---" * (len(columns) + 3) + "|")
    families: list[list[float]] = []
    for chain_name, seed in MACHINES:
        machine = held_out_machine(chain_name)
        chain = Chain.parse(chain_name)
        truth = VirtualMachine(machine, seed=seed)
        tables = fitted_tables(machine, truth, seed + 1)
        points = grid_points(machine.travel_min_mm, machine.travel_max_mm, 8)
        cells = []
        for controller in CONTROLLERS:
            ours = left_um(chain, truth, controller_model(machine, tables, controller), points)
            best = left_um(chain, truth, best_model(machine, tables, controller, truth), points)
            cells.append(f"{ours:.2f} ({best:.2f})")
        for controller in options:
            ours = left_um(chain, truth, with_option(machine, tables, controller), points)
            model = best_model(machine, tables, controller, truth, option=True)
            cells.append(f"{ours:.2f} ({left_um(chain, truth, model, points):.2f})")
        full = left_um(chain, truth, tables.model(""), points)
        none = left_um(chain, truth, None, points)
        print(f"| {chain_name} {seed} | {' | '.join(cells)} | {full:.2f} | {none:.1f} |")
        families.append(
            [left_um(chain, truth, read_back(machine, tables, *f), points) for f in FAMILIES]
        )
    print("\nthe files read back as each family's control reads them (um RMS, same machines):")
    print(f"| machine | {' | '.join(f'{c} {s}' for c, s in FAMILIES)} |")
    print("|---" * (len(FAMILIES) + 1) + "|")
    for (chain_name, seed), row in zip(MACHINES, families, strict=True):
        print(f"| {chain_name} {seed} | {' | '.join(f'{v:.2f}' for v in row)} |")


if __name__ == "__main__":
    main()
