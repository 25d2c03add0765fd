"""Benchmark: volumetric accuracy of ``post`` on machines it has never seen (issue 13).

For each seed and kinematic chain a virtual machine draws its 18 error motions
and 3 squareness errors with the amplitudes of seed 003 (Table 1); the
launch unit stands where the machine file says (station 1) and, for two
stations, also where :func:`trajectories.stations.propose_second_station` puts
it. The planner lays out the lines as ``xmalign program`` would; the rows come
from :func:`sim.synthetic.measure` with the per-sample noise of the XM-60 class
interferometer (:class:`sim.interferometer.InterferometerNoise`) and the setup
terms of docs/conventions.md. The fitted tables are compared with the truth by the
RMS volumetric difference after removing a rigid motion
(:func:`xmalign.post.compare.volumetric_rms_um`), on a grid over the measured
strokes (the box the station-1 axis lines span) and over the whole travel.

With ``--dry-run`` the calibration runs end to end on the simulator instead,
both chains: one station (:func:`sim.dry_run.simulate_calibration`) and two
(:func:`sim.two_stations.simulate_two_stations`: identify, program, run on the
virtual CNC and units at both stations, then post).

``--repeatability-um 0.5`` adds the virtual machine's positioning
repeatability (a fresh draw per point, as in :mod:`sim.machine`), which the
dry run has and which no calibration can average away beyond its runs.

Run: ``PYTHONPATH=$PWD python tests/benchmarks/bench_accuracy.py [--seeds 5] [--dry-run]
[--repeatability-um 0.5]``.
Targets: <= 0.6 um over the strokes, <= 1.0 um over the travel with two stations.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

import numpy as np

from sim.interferometer import InterferometerNoise
from sim.machine import VirtualMachine
from sim.synthetic import SetupDisturbance, measure
from trajectories.planner import plan_measurement
from trajectories.stations import propose_second_station
from xmalign.formats.plan import Plan
from xmalign.formats.pose import LaunchPose
from xmalign.machine import Machine, default_machine_path, load_machine
from xmalign.post.compare import grid_points, volumetric_rms_um
from xmalign.post.evaluate import Station, post_stations
from xmalign.rigid_body import Chain

CHAINS = ("FYXZ", "XFYZ")
STROKES_TARGET_UM = 0.6
TRAVEL_TARGET_UM = 1.0
GRID = 8


@dataclass(frozen=True)
class Figures:
    chain: str
    seed: int
    stations: int
    strokes_um: float
    travel_um: float


def _strokes(plan: Plan) -> tuple[np.ndarray, np.ndarray]:
    """The box the plan's axis lines span (each axis over its own line)."""
    low, high = np.empty(3), np.empty(3)
    for k, axis in enumerate("XYZ"):
        points = plan.line(axis).target_points_mm()[:, k]
        low[k], high[k] = points.min(), points.max()
    return low, high


def _pose(position_mm: np.ndarray) -> LaunchPose:
    """An identified pose at the station (the plan's geometry does not depend on it)."""
    covariance = np.diag([0.02**2, 0.02**2, 0.02**2, (20e-6) ** 2])
    return LaunchPose(position_mm=position_mm, gamma_rad=0.0, covariance=covariance)


def station_plans(machine: Machine, stations: int) -> list[Plan]:
    """The plans ``xmalign program`` writes for one or two launch-unit stations."""
    first = np.asarray(machine.launch_unit.position_mm, dtype=float)
    plans = [plan_measurement(machine, _pose(first)).plan]
    if stations == 2:
        second = propose_second_station(machine, first)
        plans.append(plan_measurement(machine, _pose(second.position_mm), second.line_ids).plan)
    return plans


def evaluate(machine: Machine, seed: int, stations: int, repeatability_um: float = 0.0) -> Figures:
    chain = Chain.parse(machine.chain)
    truth = VirtualMachine(machine, seed=seed)
    rng = np.random.default_rng(1000 + seed)
    noise = SetupDisturbance(
        noise=tuple(InterferometerNoise().sigmas()), repeatability_um=repeatability_um
    )
    plans = station_plans(machine, stations)
    data = [
        Station(plan, measure(plan, chain, truth, rng, setup=noise), f"station{i + 1}.csv")
        for i, plan in enumerate(plans)
    ]
    model = post_stations(machine, data).fit.tables.model("")
    low, high = _strokes(plans[0])
    strokes = volumetric_rms_um(chain, grid_points(low, high, GRID), model, truth)
    travel_points = grid_points(machine.travel_min_mm, machine.travel_max_mm, GRID)
    travel = volumetric_rms_um(chain, travel_points, model, truth)
    return Figures(machine.chain, seed, stations, strokes, travel)


def run(seeds: int, repeatability_um: float = 0.0) -> list[Figures]:
    reference = load_machine(default_machine_path())
    results = []
    print("chain  seed  stations  strokes_um  travel_um")
    for chain in CHAINS:
        machine = reference.model_copy(update={"chain": chain})
        for seed in range(seeds):
            for stations in (1, 2):
                f = evaluate(machine, seed, stations, repeatability_um)
                results.append(f)
                print(
                    f"{f.chain}   {f.seed:4d}  {f.stations:8d}  {f.strokes_um:10.2f}"
                    f"  {f.travel_um:9.2f}"
                )
    for stations in (1, 2):
        chosen = [f for f in results if f.stations == stations]
        print(
            f"{stations} station(s): strokes worst {max(f.strokes_um for f in chosen):.2f} um"
            f" (target {STROKES_TARGET_UM}), travel worst"
            f" {max(f.travel_um for f in chosen):.2f} um"
            + (f" (target {TRAVEL_TARGET_UM})" if stations == 2 else "")
        )
    return results


def run_dry(seeds: int) -> list[Figures]:
    """One and two stations end to end on the simulator, seeds 1..``seeds``, both chains."""
    import tempfile
    from pathlib import Path

    from sim.dry_run import DryRunOptions, simulate_calibration
    from sim.two_stations import simulate_two_stations

    reference = load_machine(default_machine_path())
    results = []
    print("dry run: chain  seed  1 station strokes_um  2 stations strokes_um  travel_um  min")
    for chain in CHAINS:
        machine = reference.model_copy(update={"chain": chain})
        for seed in range(1, seeds + 1):
            with tempfile.TemporaryDirectory() as folder:
                one = simulate_calibration(machine, Path(folder), DryRunOptions(seed=seed))
            with tempfile.TemporaryDirectory() as folder:
                two = simulate_two_stations(machine, Path(folder), DryRunOptions(seed=seed))
            minutes = " / ".join(f"{s.on_machine_s / 60:.1f}" for s in two.stations)
            print(
                f"{chain:>12}  {seed:4d}  {one.volumetric_after_um:20.2f}"
                f"  {two.strokes_um:21.2f}  {two.travel_um:9.2f}  {minutes}"
            )
            results.append(Figures(chain, seed, 1, one.volumetric_after_um, float("nan")))
            results.append(Figures(chain, seed, 2, two.strokes_um, two.travel_um))
    one_station = [f.strokes_um for f in results if f.stations == 1]
    two_travel = [f.travel_um for f in results if f.stations == 2]
    print(
        f"one station over the strokes: mean {np.mean(one_station):.3f},"
        f" worst {max(one_station):.3f} um (target {STROKES_TARGET_UM});"
        f" two stations over the travel: mean {np.mean(two_travel):.3f},"
        f" worst {max(two_travel):.3f} um (target {TRAVEL_TARGET_UM})"
    )
    return results


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--dry-run", action="store_true", help="end to end on the simulator")
    parser.add_argument(
        "--repeatability-um",
        type=float,
        default=0.0,
        help="machine positioning repeatability (the dry run's virtual machine has 0.5)",
    )
    arguments = parser.parse_args()
    if arguments.dry_run:
        run_dry(arguments.seeds)
    else:
        run(arguments.seeds, arguments.repeatability_um)
