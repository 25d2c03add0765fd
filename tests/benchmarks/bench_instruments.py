"""Benchmark: laser tracker, laser tracers and the XM-60 in one fit (issue 24).

On machines ``post`` has never seen (:class:`sim.machine.VirtualMachine`, seed
003's error amplitudes, 0.5 um repeatability; seeds 0.. of both chains, FYXZ
``examples/fyxz.yaml`` and the same machine as XFYZ, as in bench_accuracy.py):

- **tracker alone**: one station on the table in the middle of the travel, 300 mm
  below the lowest tool point, turned by (0.5, -1, 30) degrees; 250 points
  (a 5 x 4 x 3 grid over the travel plus 190 random points, seed 000's strategy)
  measured twice; noise half the published MPE (:mod:`sim.tracker`);
- **tracker on the fly** (seed 001): the same station, the machine moving at
  5000 mm/min along 47 axis-parallel paths (every axis end to end at the 5 x 4 x 3
  grid's coordinates of the other two) and 24 diagonal paths across the volume,
  the tracker sampling every 20 mm; only the deviation across each path counts.
  The simulated tracker's noise is independent from sample to sample, which
  flatters the many samples on the fly (a real tracker's angular errors are partly
  systematic over a stretch of path);
- **tracers alone**: four places near the table's corners at two heights, 440
  points each (the grid plus 380 random points), one run each (seed 004);
  noise half the LaserTRACER's U (:mod:`sim.tracer`);
- **XM-60 station alone** and **with the tracker**: the six lines of station 1
  (:func:`sim.instrument_study.station_plan`, the plan of bench_accuracy.py's
  station 1; interferometer noise and setup terms of :func:`sim.synthetic.measure`)
  without and with the tracker's 250 x 2 points.

The measurements are :mod:`sim.instrument_study`'s (also ``xmalign mc --mode
instruments``).

The SMR sits 100 mm below the tool point. Figures: RMS volumetric difference
from the truth after removing a rigid motion, 8 x 8 x 8 grid over the whole
travel (and over the interferometer's strokes for the XM-60 rows). Without
interferometer lines the tables are those of the SMR as the functional point
(docs/post.md), so tracker and tracer rows compare with the truth at the SMR.
Machine time: the G-code :func:`trajectories.instruments.write_instrument_program`
writes (points in nearest-neighbour order, straight moves at the rapid feed, 3 s
per point; paths at 5000 mm/min), the XM-60 program's own estimate
(:func:`trajectories.gcode.program.estimate_machine_time`).

Run: ``PYTHONPATH=$PWD python tests/benchmarks/bench_instruments.py [--seeds 5]``;
with ``--sizes`` the tracker and tracers across machine sizes with one and three SMR
positions instead (:mod:`bench_instrument_sizes`).
Targets (issue 24): tracker alone about 4 um or better; tracers alone <= 1.0 um;
XM-60 + tracker over the travel <= 0.8 x the XM-60 alone, over the strokes at
most 0.15 um worse than the XM-60 alone.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))  # bench_accuracy: the strokes' box

from bench_accuracy import _strokes  # noqa: E402
from bench_instrument_sizes import run as run_sizes  # noqa: E402

from sim.instrument_study import (  # noqa: E402
    station_plan,
    tracer_file,
    tracker_file,
    tracker_fly_file,
    xm60_station,
)
from sim.machine import VirtualMachine  # noqa: E402
from trajectories.gcode.program import estimate_machine_time  # noqa: E402
from xmalign.machine import Machine, default_machine_path, load_machine  # noqa: E402
from xmalign.post.compare import grid_points, volumetric_rms_um  # noqa: E402
from xmalign.post.evaluate import Instruments, post_stations  # noqa: E402
from xmalign.rigid_body import Chain  # noqa: E402

CHAINS = ("FYXZ", "XFYZ")
SMR_OFFSET_MM = (0.0, 0.0, -100.0)
GRID = 8
TRACKER_TARGET_UM = 4.0
TRACER_TARGET_UM = 1.0
TRAVEL_RATIO_TARGET = 0.8
STROKES_MARGIN_UM = 0.15


@dataclass(frozen=True)
class Figures:
    chain: str
    seed: int
    tracker_um: float
    tracker_fly_um: float
    tracers_um: float
    limits_um: tuple[float, float, float]
    xm60_strokes_um: float
    xm60_travel_um: float
    joint_strokes_um: float
    joint_travel_um: float
    post_s: float


def evaluate(machine: Machine, seed: int) -> tuple[Figures, dict[str, float]]:
    chain = Chain.parse(machine.chain)
    truth = VirtualMachine(machine, seed=seed)
    travel = grid_points(machine.travel_min_mm, machine.travel_max_mm, GRID)
    trackers, tracker_min = tracker_file(machine, truth, seed)
    tracers, tracer_min = tracer_file(machine, truth, seed)
    fly, fly_min = tracker_fly_file(machine, truth, seed)
    tracker_only = post_stations(machine, [], instruments=Instruments(trackers=(trackers,)))
    fly_only = post_stations(machine, [], instruments=Instruments(trackers=(fly,)))
    tracer_only = post_stations(machine, [], instruments=Instruments(tracers=(tracers,)))

    plan = station_plan(machine)
    stations = [xm60_station(machine, truth, seed, plan)]
    alone = post_stations(machine, stations)
    started = time.perf_counter()
    joint = post_stations(machine, stations, instruments=Instruments(trackers=(trackers,)))
    post_s = time.perf_counter() - started
    strokes = grid_points(*_strokes(plan), GRID)

    def rms(result, points: np.ndarray, at_smr: bool = False) -> float:
        model = result.fit.tables.model("")
        offset = machine.smr_offset if at_smr else None
        return volumetric_rms_um(chain, points, model, truth, offset)

    figures = Figures(
        chain=machine.chain,
        seed=seed,
        tracker_um=rms(tracker_only, travel, at_smr=True),
        tracker_fly_um=rms(fly_only, travel, at_smr=True),
        tracers_um=rms(tracer_only, travel, at_smr=True),
        limits_um=tuple(
            r.instruments.volumetric_u_um(chain, travel)
            for r in (tracker_only, fly_only, tracer_only)
        ),
        xm60_strokes_um=rms(alone, strokes),
        xm60_travel_um=rms(alone, travel),
        joint_strokes_um=rms(joint, strokes),
        joint_travel_um=rms(joint, travel),
        post_s=post_s,
    )
    minutes = {
        "tracker": tracker_min,
        "tracker on the fly": fly_min,
        "tracers": tracer_min,
        "xm60": estimate_machine_time(plan, machine).total_s / 60,
    }
    return figures, minutes


def run(seeds: int) -> list[Figures]:
    reference = load_machine(default_machine_path()).model_copy(
        update={"smr_offset_mm": list(SMR_OFFSET_MM)}
    )
    results = []
    print(
        "chain  seed  tracker_um  on-the-fly_um  tracers_um  xm60 strokes/travel_um"
        "  xm60+tracker strokes/travel_um  ratio  post_s"
    )
    minutes: dict[str, float] = {}
    for chain in CHAINS:
        machine = reference.model_copy(update={"chain": chain})
        for seed in range(seeds):
            f, minutes = evaluate(machine, seed)
            results.append(f)
            print(
                f"{f.chain}  {f.seed:4d}  {f.tracker_um:10.2f}  {f.tracker_fly_um:13.2f}"
                f"  {f.tracers_um:10.2f}"
                f"  {f.xm60_strokes_um:10.2f} / {f.xm60_travel_um:5.2f}"
                f"  {f.joint_strokes_um:18.2f} / {f.joint_travel_um:5.2f}"
                f"  {f.joint_travel_um / f.xm60_travel_um:5.2f}  {f.post_s:6.1f}"
            )
    limits = np.array([f.limits_um for f in results])
    print(
        "information limit (RMS standard uncertainty of the fitted volumetric error over the"
        " travel, from the fit's covariance): tracker "
        + ", ".join(
            f"{name} {low:.2f}-{high:.2f} um"
            for name, low, high in zip(
                ("alone", "on the fly", "tracers"),
                limits.min(axis=0),
                limits.max(axis=0),
                strict=True,
            )
        )
    )
    print(
        "machine time (min): "
        + ", ".join(f"{name} {value:.0f}" for name, value in minutes.items())
        + " (XM-60: one station, six lines, without setting the units)"
    )
    _summary(results)
    return results


def _summary(results: list[Figures]) -> None:
    tracker = [f.tracker_um for f in results]
    fly = [f.tracker_fly_um for f in results]
    tracers = [f.tracers_um for f in results]
    ratio = [f.joint_travel_um / f.xm60_travel_um for f in results]
    strokes = [f.joint_strokes_um - f.xm60_strokes_um for f in results]
    print(
        f"tracker alone: mean {np.mean(tracker):.2f}, worst {max(tracker):.2f} um"
        f" (target about {TRACKER_TARGET_UM})"
    )
    print(f"tracker on the fly: mean {np.mean(fly):.2f}, worst {max(fly):.2f} um")
    print(
        f"tracers alone: mean {np.mean(tracers):.2f}, worst {max(tracers):.2f} um"
        f" (target {TRACER_TARGET_UM})"
    )
    print(
        f"XM-60 + tracker over the travel: ratio to XM-60 alone mean {np.mean(ratio):.2f},"
        f" worst {max(ratio):.2f} (target {TRAVEL_RATIO_TARGET}); over the strokes worse by at"
        f" most {max(strokes):+.2f} um (target {STROKES_MARGIN_UM})"
    )


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--sizes", action="store_true", help="across machine sizes and SMRs")
    arguments = parser.parse_args()
    (run_sizes if arguments.sizes else run)(arguments.seeds)
