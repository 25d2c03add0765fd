"""The live commands end to end against ``xmalign sim serve`` processes, as on a shop floor.

One ``sim serve`` process serves a whole virtual world on 127.0.0.1: both
units over Modbus TCP, the interferometer on a pty and a CNC that runs the
plan's G-code on cycle start (Enter on its standard input) and writes its
position to a file. ``xmalign run --config`` runs in another process; the test
plays the operator: it presses cycle start when the run says so, interrupts
the run, kills the server. The plan is one short line (3 targets, one run each
way) on a machine at 20 m/min, so that a
complete run takes some 10 s of real time. ``identify --live`` against the same
harness: test_live_identify_e2e.py (a module of its own, so that pytest-xdist runs it
next to this one).
"""

from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml
from cli_helpers import Process

from sim.alignment_setup import point_by_truth
from sim.units import SimPositioningUnit
from sim.world import build_world
from trajectories.gcode import make_dialect
from trajectories.gcode.program import write_program
from xmalign.calibration import capture_sequence
from xmalign.formats.measurements import load_measurements
from xmalign.formats.plan import read_plan
from xmalign.formats.pose import LaunchPose, write_pose
from xmalign.machine import Machine, load_machine

ROOT = Path(__file__).resolve().parents[2]
SEED = 4
GAMMA_DEG = -60.0
ENV = {**os.environ, "COLUMNS": "200", "PYTHONPATH": str(ROOT)}


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class World:
    """``xmalign sim serve`` of a world: both units, the interferometer, and with a
    ``program`` a CNC that runs it (else the machine stands at the travel's centre)."""

    def __init__(self, workdir: Path, program: Path | None = None) -> None:
        self.workdir = workdir
        self.position_file = workdir / "position.txt"
        self.ports = ports = [_free_port(), _free_port()]
        args = ["sim", "serve", "--seed", str(SEED), "--gamma-deg", str(GAMMA_DEG)]
        args += ["--modbus", str(ports[0]), "--modbus-receiver", str(ports[1])]
        args += ["--interferometer-pty"]
        if program is not None:
            args += ["--machine", "machine.yaml", "--program", str(program)]
            args += ["--position-file", str(self.position_file)]
        self.server = Process(args, workdir, stdin=subprocess.PIPE)
        pty = self.server.wait_for("interferometer on").split()[-1]
        # the CNC's first report comes from its own thread: it must not be taken later
        # for the report of a stop the CNC has not yet reached
        self.server.wait_for_all("serving", *(["waiting for cycle start"] if program else []))
        self.config = workdir / "units.yaml"
        position = f"{{source: file, file: {self.position_file.name}}}" if program else "{}"
        self.config.write_text(
            "format: xmalign.units/1\n"
            f"launch: {{transport: modbus-tcp, host: 127.0.0.1, port: {ports[0]}}}\n"
            f"receiver: {{transport: modbus-tcp, host: 127.0.0.1, port: {ports[1]}}}\n"
            f"interferometer: {{port: {pty}, rate_hz: 50}}\n"
            f"machine_position: {position}\n"
            "timeouts: {io_s: 1.0, move_s: 30.0}\n"
        )

    def cycle_start(self) -> None:
        """The operator presses cycle start on the CNC."""
        stdin = self.server.popen.stdin
        assert stdin is not None
        stdin.write("\n")
        stdin.flush()


def _truth_pose(machine: Machine) -> LaunchPose:
    """The served world's true launch pose (the same seed builds the same world)."""
    world = build_world(machine, seed=SEED, gamma_rad=math.radians(GAMMA_DEG))
    offsets = world.offsets
    return LaunchPose(
        world.launch2mcs_mm,
        world.gamma_rad,
        np.diag([1e-4, 1e-4, 1e-4, 1e-10]),
        {"c2": offsets.c2, "c3": offsets.c3, "c4": offsets.c4},
    )


def quick_machine(reference_machine_path: Path, folder: Path, try_out: bool = False) -> Path:
    """The reference machine at 20 m/min as ``folder/machine.yaml``; ``try_out``: targets
    10 mm apart and one run each way, so that ``program --max-length-mm 20`` plans three
    targets per line (a try-out as a user would set one up)."""
    quick = yaml.safe_load(reference_machine_path.read_text())
    quick["feed_mm_min"] = {"rapid": 20000, "measure": 20000}
    quick["cnc"] = {"acceleration_mm_s2": 5000}
    if try_out:
        quick["measurement"] = {
            **quick.get("measurement", {}),
            "target_spacing_mm": 10.0,
            "runs": 1,
            "diagonal_runs": 1,
        }
    path = folder / "machine.yaml"
    path.write_text(yaml.safe_dump(quick))
    return path


def try_out_plan(workdir: Path, reference_machine_path: Path, lines: tuple[str, ...]) -> Path:
    """The quick try-out machine (:func:`quick_machine`), the true pose and the plan of
    ``lines`` (all six: ``()``) from ``xmalign program --max-length-mm 20``: each line
    cut to 20 mm, three targets, one run each way. Returns ``workdir``."""
    machine = load_machine(quick_machine(reference_machine_path, workdir, try_out=True))
    write_pose(workdir / "pose.json", _truth_pose(machine))
    subprocess.run(
        [sys.executable, "-m", "xmalign", "program", "--machine", "machine.yaml"]
        + (["--lines", ",".join(lines)] if lines else [])
        + ["--max-length-mm", "20", "--plan-out", "plan.json"],
        cwd=workdir,
        env=ENV,
        check=True,
        capture_output=True,
    )
    return workdir


@pytest.fixture(scope="module")
def short_plan(tmp_path_factory: pytest.TempPathFactory, reference_machine_path: Path) -> Path:
    """A quick machine (the reference one at 20 m/min) and its plan and program for line Z
    from the true pose, the line cut to 20 mm: machine.yaml, plan.json and run.nc."""
    workdir = try_out_plan(tmp_path_factory.mktemp("plan"), reference_machine_path, ("Z",))
    machine = load_machine(workdir / "machine.yaml")
    plan = read_plan(workdir / "plan.json")
    (workdir / "run.nc").write_text(
        write_program(plan, machine, make_dialect("sinumerik", machine))
    )
    return workdir


@pytest.fixture
def world(short_plan: Path, tmp_path: Path) -> Iterator[World]:
    for name in ("machine.yaml", "plan.json", "run.nc"):
        (tmp_path / name).write_bytes((short_plan / name).read_bytes())
    served = World(tmp_path, tmp_path / "run.nc")
    yield served
    served.server.stop()


def _start_run(world: World, *extra: str) -> Process:
    return Process(
        ["run", "--config", "units.yaml", "--machine", "machine.yaml"]
        + ["--plan", "plan.json", "--out", "m.csv", *extra],
        world.workdir,
    )


def _keys(path: Path) -> list[tuple]:
    return [(r.line, r.run, r.direction, r.index) for r in load_measurements(path).rows]


def _expected_keys(plan_path: Path) -> list[tuple]:
    line = read_plan(plan_path).lines[0]
    return [(line.id, p.run, p.direction, p.index) for p in capture_sequence(line)]


def _run_to_line_start(world: World) -> Process:
    """Cycle start: the CNC goes to the line start and stops (M0); the run sets the units."""
    world.cycle_start()
    world.server.wait_for("program started")
    world.server.wait_for("waiting for cycle start")
    run = _start_run(world)
    run.wait_for("press cycle start")
    world.cycle_start()
    return run


def _wait_for_rows(path: Path, count: int, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if path.exists() and len(load_measurements(path, torn_ok=True).rows) >= count:
            return
        time.sleep(0.05)
    raise AssertionError(f"{path} holds fewer than {count} points after {timeout_s} s")


def test_live_run_captures_every_point_of_the_plan(world: World) -> None:
    run = _run_to_line_start(world)
    assert run.finish() == 0, run.stderr
    out = world.workdir / "m.csv"
    assert _keys(out) == _expected_keys(world.workdir / "plan.json")
    assert "7 points captured; 7 points in m.csv" in "".join(run.lines)
    assert "Traceback" not in run.stderr
    rows = load_measurements(out).rows
    # captured where the plan says, with the beam well inside the ±250 µm straightness range
    targets = read_plan(world.workdir / "plan.json").lines[0].target_points_mm()
    assert all(np.allclose(r.machine_mm, targets[r.index], atol=0.005) for r in rows)
    assert max(np.abs(r.channels[1:3]).max() for r in rows) < 100.0
    # each reading of a machine standing still: the linear error over 20 mm is some µm, not the
    # millimetres of a machine averaged while it moves on (two stops at one place: see
    # xmalign.calibration.follow_machine)
    assert max(abs(r.channels[0]) for r in rows) < 20.0
    world.server.wait_for("program end")


def test_live_run_interrupted_then_resumed_loses_and_repeats_no_point(world: World) -> None:
    out = world.workdir / "m.csv"
    run = _run_to_line_start(world)
    _wait_for_rows(out, 2)
    run.popen.send_signal(signal.SIGINT)
    assert run.finish() == 130
    kept = load_measurements(out, torn_ok=True).rows
    assert len(kept) >= 2
    assert f"stopped: {len(kept)} points kept in m.csv; go on with --resume" in run.stderr
    assert "Traceback" not in run.stderr
    world.server.wait_for("program end")  # the CNC ran on to the program's end
    resumed = _start_run(world, "--resume", "--log-file", "wire.log")
    resumed.wait_for("waiting for the machine to stop at the pre-position of line")
    world.cycle_start()  # runs the program again from the top: to the line start, M0
    world.server.wait_for("program started")
    world.server.wait_for("waiting for cycle start")
    resumed.wait_for("press cycle start")
    world.cycle_start()
    assert resumed.finish() == 0, resumed.stderr
    assert _keys(out) == _expected_keys(world.workdir / "plan.json")
    rows = load_measurements(out).rows
    assert max(abs(r.channels[0]) for r in rows) < 20.0
    again = rows[: len(kept)]
    assert all(np.array_equal(a.channels, b.channels) for a, b in zip(again, kept, strict=True))


def test_server_killed_mid_run_one_line_and_the_points_kept(world: World) -> None:
    out = world.workdir / "m.csv"
    run = _run_to_line_start(world)
    _wait_for_rows(out, 2)
    world.server.popen.kill()
    world.server.popen.wait()
    code = run.finish()
    assert code not in (0, 130)
    lines = [line for line in run.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("xmalign: error: "), run.stderr
    saved = len(load_measurements(out, torn_ok=True).rows)
    assert saved >= 2
    assert f"{saved} points kept in m.csv" in lines[0]


def test_align_live_manual_then_fine_against_sim_serve(
    tmp_path: Path, reference_machine: Machine
) -> None:
    """The operator jogs each axis to where the beam is in range, then fine alignment."""
    served = World(tmp_path)
    try:
        truth = build_world(reference_machine, seed=SEED, gamma_rad=math.radians(GAMMA_DEG))
        launch, receiver = SimPositioningUnit(truth.launch), SimPositioningUnit(truth.receiver)
        start = np.concatenate([launch.angles_rad(), receiver.angles_rad()])
        point_by_truth(truth, reference_machine, launch, receiver)
        jogs = np.concatenate([launch.angles_rad(), receiver.angles_rad()]) - start
        typed = "\na9 1\n" + "".join(
            f"a{n} {math.degrees(step):.6f}\n" for n, step in enumerate(jogs, start=1)
        )
        result = subprocess.run(
            [sys.executable, "-m", "xmalign", "align", "--live", "--manual"]
            + ["--config", "units.yaml", "--log-file", "wire.log"],
            cwd=tmp_path,
            env=ENV,
            input=typed + "\n",
            capture_output=True,
            text=True,
            timeout=120,
        )
    finally:
        served.server.stop()
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stdout.count("beam out of range") >= 2
    assert "the beam is not in range yet" in result.stdout  # Enter before the beam is in range
    assert "jog command 'a9 1': expected an axis a1..a5" in result.stdout
    assert "beam in range:" in result.stdout
    assert "s of wall time" in result.stdout and "units locked" in result.stdout
    assert "write axis1.control @16 <- [9] = 9" in (tmp_path / "wire.log").read_text()


def _align_waiting_at_the_jog_prompt(served: World) -> Process:
    """``align --live --manual`` started against the served world, at its first report."""
    align = Process(
        ["align", "--live", "--manual", "--config", "units.yaml", "--log-file", "wire.log"],
        served.workdir,
        stdin=subprocess.PIPE,
    )
    align.wait_for("beam out of range")
    return align


def test_align_live_stopped_by_ctrl_c_locks_the_units(tmp_path: Path) -> None:
    served = World(tmp_path)
    try:
        align = _align_waiting_at_the_jog_prompt(served)
        align.popen.send_signal(signal.SIGINT)
        assert align.finish() == 130, align.stderr
    finally:
        served.server.stop()
    (line,) = align.stderr.strip().splitlines()
    assert line == "xmalign: interrupted by the operator; all axes were stopped and locked"
    wire = (tmp_path / "wire.log").read_text()
    assert "write axis1.control @16 <- [9] = 9" in wire  # a lock on each unit's first axis
    assert wire.count("axis1.control @16 <- [9]") >= 2


def test_align_live_with_the_server_killed_is_one_line(tmp_path: Path) -> None:
    served = World(tmp_path)
    try:
        align = _align_waiting_at_the_jog_prompt(served)
        served.server.popen.kill()
        served.server.popen.wait()
        assert align.popen.stdin is not None
        align.popen.stdin.write("a1 1.0\n")
        align.popen.stdin.close()
        code = align.finish()
    finally:
        served.server.stop()
    assert code == 2, align.stderr
    (line,) = align.stderr.strip().splitlines()
    assert line.startswith("xmalign: error:") and "launch unit" in line, line
