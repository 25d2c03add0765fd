"""Benchmark: tracker and tracers across machine sizes, one and three SMR positions (issue 30).

On three machines (:class:`sim.machine.VirtualMachine`, seed 003's error
amplitudes, 0.5 um repeatability, FYXZ):

- **seed 004's gantry**: X [-800, 0], Y [-1000, 0], Z [-350, 0], E_C0Y 2900 urad
  (its Table 7), the tracers at its Table 6 pivots (all on one side, 100 mm below
  the table's SMR level, as the SMR sits 100 mm below the tool point);
- **the reference machine** (``examples/fyxz.yaml``, 2000 x 1500 x 500 mm);
- **a large one**: 5000 x 3000 x 1000 mm.

Each measured by

- the **tracker alone** (seed 000's 5 x 4 x 3 grid and 190 random points, twice;
  :func:`sim.instrument_study.tracker_file`'s station), and
- **four tracers** (``propose_tracer_places``, or seed 004's places on its machine;
  the grid and 380 random points from each),

with **one SMR position** (100 mm below the tool point: the tables are the SMR's)
or **three** (A 100 mm below, B 100 mm in +X and C 100 mm in +Y, both 60 mm below:
the tables are the tool point's, all 21 errors). Figures: RMS volumetric residual
over an 8 x 8 x 8 grid of the whole travel after a rigid motion, at the tables'
functional point, beside the information limit (the fit's covariance propagated
there: what the readings' noise leaves), and at a tool 250 mm long with an 80 mm
lateral offset; the knot spacing cross-validation chose; post's time.

Run: ``PYTHONPATH=$PWD python tests/benchmarks/bench_instrument_sizes.py [--seeds 2]``.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import numpy as np

from sim.machine import VirtualMachine
from sim.tracer import VirtualTracer, measure_tracer
from sim.tracker import VirtualTracker, measure_tracker
from trajectories.instruments import (
    propose_tracer_places,
    tracer_points,
    tracker_place,
    tracker_points,
)
from xmalign.formats.instruments import TracerFile, TrackerFile
from xmalign.machine import Machine, default_machine_path, load_machine
from xmalign.post.compare import grid_points, remove_rigid_motion
from xmalign.post.evaluate import Instruments, post_stations
from xmalign.rigid_body import Chain, deviation

SMR_MM = (0.0, 0.0, -100.0)
SMR_POSITIONS_MM = {"A": [0.0, 0.0, -100.0], "B": [100.0, 0.0, -60.0], "C": [0.0, 100.0, -60.0]}
TOOL_MM = np.array([80.0, 0.0, -250.0])
SEED_004_PIVOTS_MM = np.array(
    [
        [158.8075, -1456.6824, -349.7023],
        [-113.1165, -1671.7155, -349.3517],
        [-468.6489, -1563.1627, -349.4140],
        [-769.8987, -1599.5469, -208.9567],
    ]
)
TRACKER_ROTATION_DEG = (0.5, -1.0, 30.0)
GRID = 8
SIZES = {
    "seed 004 gantry": {"X": [-800, 0], "Y": [-1000, 0], "Z": [-350, 0]},
    "reference": None,
    "large": {"X": [0, 5000], "Y": [0, 3000], "Z": [-1000, 0]},
}


@dataclass(frozen=True)
class Row:
    size: str
    instrument: str
    smr: str
    seed: int
    residual_um: float
    limit_um: float
    at_tool_um: float
    spacing_mm: float
    post_s: float


def machine_of(size: str) -> Machine:
    base = load_machine(default_machine_path()).model_copy(
        update={"smr_offset_mm": list(SMR_MM), "smr_offsets_mm": SMR_POSITIONS_MM}
    )
    travel = SIZES[size]
    return base if travel is None else base.model_copy(update={"travel_mm": travel})


def truth_of(machine: Machine, size: str, seed: int) -> VirtualMachine:
    truth = VirtualMachine(machine, seed=seed)
    if size == "seed 004 gantry":
        truth._squareness[0] = 2900e-6  # seed 004, Table 7
    return truth


def measure(
    machine: Machine, size: str, truth: VirtualMachine, instrument: str, three: bool, seed: int
) -> Instruments:
    named = machine.smr_offsets() if three else None
    if instrument == "tracker":
        tracker = VirtualTracker(tracker_place(machine), np.array(TRACKER_ROTATION_DEG), seed=seed)
        points = tracker_points(machine, seed)
        rows = measure_tracker(truth, tracker, points, 2, machine.smr_offset, smr_offsets_mm=named)
        return Instruments(trackers=(TrackerFile(rows, "tracker.csv"),))
    pivots = (
        list(SEED_004_PIVOTS_MM + [0, 0, -100])
        if size == "seed 004 gantry"
        else propose_tracer_places(machine, 4)
    )
    lengths = []
    for i, pivot in enumerate(pivots):
        tracer = VirtualTracer(np.asarray(pivot, float), seed=10 * seed + i)
        points = tracer_points(machine, 10 * seed + i)
        lengths += measure_tracer(
            truth, tracer, points, 1, machine.smr_offset, f"P{i + 1}", smr_offsets_mm=named
        )
    return Instruments(tracers=(TracerFile(lengths, "tracer.csv"),))


def evaluate(size: str, instrument: str, three: bool, seed: int) -> Row:
    machine = machine_of(size)
    truth = truth_of(machine, size, seed)
    instruments = measure(machine, size, truth, instrument, three, seed)
    started = time.perf_counter()
    result = post_stations(machine, [], instruments=instruments)
    post_s = time.perf_counter() - started
    joint = result.instruments
    assert joint is not None
    chain = Chain.parse(machine.chain)
    grid = grid_points(machine.travel_min_mm, machine.travel_max_mm, GRID)
    model = result.fit.tables.model("")
    # one SMR: the tables are the SMR's (compared there); three: the tool point's
    functional = np.zeros(3) if three else machine.smr_offset
    tool = TOOL_MM if three else TOOL_MM - machine.smr_offset
    return Row(
        size=size,
        instrument=instrument,
        smr="three" if three else "one",
        seed=seed,
        residual_um=_at_tool_um(chain, grid, model, truth, np.zeros(3), functional),
        limit_um=joint.volumetric_u_um(chain, grid),
        at_tool_um=_at_tool_um(chain, grid, model, truth, tool, TOOL_MM),
        spacing_mm=float(joint.knot_spacing_mm or 0.0),
        post_s=post_s,
    )


def _at_tool_um(chain: Chain, grid, model, truth, model_offset, true_offset) -> float:
    """The tables used for a tool (their functional point moved by ``model_offset``)."""
    fitted, _ = deviation(chain, grid, model_offset, model)
    true, _ = deviation(chain, grid, true_offset, truth)
    residual = remove_rigid_motion(grid, fitted - true)
    return float(np.sqrt(np.mean(np.sum(residual**2, axis=1))) * 1e3)


def run(seeds: int) -> list[Row]:
    rows = []
    print(
        "machine          instrument  SMR    seed  residual_um  limit_um  at-tool_um"
        "  spacing_mm  post_s"
    )
    for size in SIZES:
        for instrument in ("tracker", "tracers"):
            for three in (False, True):
                for seed in range(seeds):
                    r = evaluate(size, instrument, three, seed)
                    rows.append(r)
                    print(
                        f"{r.size:16s} {r.instrument:10s}  {r.smr:5s}  {r.seed:4d}"
                        f"  {r.residual_um:11.2f}  {r.limit_um:8.2f}  {r.at_tool_um:10.2f}"
                        f"  {r.spacing_mm:10.0f}  {r.post_s:6.1f}",
                        flush=True,
                    )
    print("summary (mean over seeds): residual / limit / at the tool, um")
    for size in SIZES:
        for instrument in ("tracker", "tracers"):
            for smr in ("one", "three"):
                group = [
                    r for r in rows if (r.size, r.instrument, r.smr) == (size, instrument, smr)
                ]
                print(
                    f"{size:16s} {instrument:10s} {smr:5s}"
                    f" {np.mean([r.residual_um for r in group]):6.2f}"
                    f" / {np.mean([r.limit_um for r in group]):6.2f}"
                    f" / {np.mean([r.at_tool_um for r in group]):6.2f}"
                )
    return rows


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=2)
    run(parser.parse_args().seeds)
