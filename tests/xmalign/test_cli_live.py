"""The live paths of ``run``, ``identify`` and ``align`` in this process, over the real protocols.

The seed-3 virtual setup is served as a technician finds real hardware: both
units over Modbus TCP on 127.0.0.1, the interferometer on a pty. The operator is a script
at the terminal (``sys.stdin``/``sys.stdout``): it reads what xmalign asks, moves the
virtual machine where it is told and answers, or jogs, or presses Ctrl-C.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import re
import signal
import subprocess
import textwrap
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import assert_one_line_error, free_port, run_in_process

from sim.dry_run import VirtualSetup, virtual_setup
from sim.servers.modbus import ModbusUnitServer
from sim.servers.serial_pty import PtyInterferometerServer
from sim.world import FixedPosition
from trajectories.gcode import make_dialect, resolve_dialect
from trajectories.gcode.program import write_program
from trajectories.planner import plan_measurement
from xmalign.calibration import capture_sequence
from xmalign.formats.measurements import read_measurements
from xmalign.formats.plan import read_plan, write_plan
from xmalign.formats.pose import LaunchPose, read_pose

SEED = 3
#: What xmalign tells the operator before each move of the machine (OperatorPrompt).
MOVE = re.compile(r"Move the machine to X(\S+) Y(\S+) Z(\S+)")


@pytest.fixture(scope="module")
def plans(tmp_path_factory, reference_machine):
    """Lines Z and X planned for the true pose of the seed-3 virtual setup (a perfect
    identification), the G-code program of both."""
    world = virtual_setup(reference_machine, SEED).world
    offsets = world.offsets
    pose = LaunchPose(
        world.launch2mcs_mm,
        world.gamma_rad,
        np.diag([1e-4, 1e-4, 1e-4, 1e-10]),
        {"c2": offsets.c2, "c3": offsets.c3, "c4": offsets.c4},
        n_alignments=6,
    )
    folder = tmp_path_factory.mktemp("plans")
    plan = plan_measurement(reference_machine, pose, ("Z", "X")).plan
    write_plan(folder / "plan.json", plan)
    dialect = make_dialect(resolve_dialect(reference_machine, None), reference_machine)
    (folder / "run.nc").write_text(write_program(plan, reference_machine, dialect))
    return folder


@pytest.fixture
def short_plan(plans, tmp_path):
    """Line Z cut to three targets, one bidirectional run, short dwell."""
    data = json.loads((plans / "plan.json").read_text())
    line = next(line for line in data["lines"] if line["id"] == "Z")
    line.update(targets_mm=line["targets_mm"][:3], runs=1, bidirectional=True, dwell_s=0.1)
    data["lines"] = [line]
    path = tmp_path / "plan.json"
    path.write_text(json.dumps(data))
    return path


class Terminal:
    """The operator's terminal: what xmalign prints, and a script that answers its prompts.

    ``answer(printed)`` gets the text printed since the last prompt and returns the line
    typed (None: end of input); it may raise KeyboardInterrupt as a Ctrl-C.
    """

    def __init__(self, answer: Callable[[str], str | None]) -> None:
        self.out = io.StringIO()
        self.answer = answer
        self.prompts = 0
        self._seen = 0

    def readline(self) -> str:
        text = self.out.getvalue()
        printed, self._seen = text[self._seen :], len(text)
        self.prompts += 1
        reply = self.answer(printed)
        return "" if reply is None else reply + "\n"


def xmalign(terminal: Terminal, *args: str) -> subprocess.CompletedProcess:
    """``xmalign ARGS`` in this process at ``terminal``: exit code, stdout, stderr."""
    return run_in_process(*args, stdin=terminal, stdout=terminal.out)


@dataclass
class Served:
    """A virtual setup served over the real protocols, and the units.yaml that names it."""

    setup: VirtualSetup
    machine: FixedPosition
    launch: ModbusUnitServer
    receiver: ModbusUnitServer
    interferometer: PtyInterferometerServer
    config: Path

    def axes(self) -> list:
        world = self.setup.world
        return [*world.launch.axes, *world.receiver.axes]


@contextlib.contextmanager
def served(
    machine, folder: Path, plan_path: Path | None = None, position_mm=None
) -> Iterator[Served]:
    """Serve the seed-3 virtual setup; the units stand at the plan's first line's angles.

    The units are set in simulated time, then the clock follows the wall clock, as the
    served devices of ``xmalign sim serve`` do.
    """
    setup = virtual_setup(machine, SEED)
    world = setup.world
    position = FixedPosition(setup.cnc.position_mm() if position_mm is None else position_mm)
    world.interferometer.position = position
    if plan_path is not None:
        line = read_plan(plan_path).lines[0]
        setup.launch.move_to(line.launch_rad, 30.0)
        setup.receiver.move_to(line.receiver_rad, 30.0)
    world.clock.follow_wall_clock()
    launch = ModbusUnitServer(world.launch, "127.0.0.1", free_port())
    receiver = ModbusUnitServer(world.receiver, "127.0.0.1", free_port())
    pty = PtyInterferometerServer(world.interferometer, rate_hz=200.0)
    started = []
    try:
        for server in (launch, receiver, pty):
            server.start()
            started.append(server)
        config = folder / "units.yaml"
        config.write_text(
            textwrap.dedent(f"""\
            format: xmalign.units/1
            launch: {{transport: modbus-tcp, host: 127.0.0.1, port: {launch.port}}}
            receiver: {{transport: modbus-tcp, host: 127.0.0.1, port: {receiver.port}}}
            interferometer: {{port: {pty.port}, rate_hz: 200}}
            timeouts: {{io_s: 0.5, move_s: 15.0}}
            """)
        )
        yield Served(setup, position, launch, receiver, pty, config)
    finally:
        for server in reversed(started):
            with contextlib.suppress(Exception):
                server.stop()


def moving_operator(
    position: FixedPosition, then: Callable[[int], None] = lambda prompt: None
) -> Callable[[str], str | None]:
    """An operator who moves the machine where told and presses Enter (the target as typed).

    ``then(n)`` is called at the n-th prompt first (n from 1): to press Ctrl-C, pull a cable.
    """
    count = [0]

    def answer(printed: str) -> str | None:
        count[0] += 1
        then(count[0])
        moves = MOVE.findall(printed)
        assert moves, f"asked without a move: {printed!r}"
        position.position = np.array([float(v) for v in moves[-1]])
        return ""

    return answer


def _points(plan_path: Path) -> list[tuple]:
    plan = read_plan(plan_path)
    return sorted(
        (p.line.id, p.run, p.direction, p.index)
        for line in plan.lines
        for p in capture_sequence(line)
    )


def _keys(csv_path: Path) -> list[tuple]:
    return sorted((r.line, r.run, r.direction, r.index) for r in read_measurements(csv_path))


def _run(terminal: Terminal, world: Served, plan: Path, out: Path, *extra: str):
    return xmalign(
        terminal,
        "run",
        "--plan",
        str(plan),
        "--config",
        str(world.config),
        "--out",
        str(out),
        *extra,
    )


def _run_with_a_fifth_prompt_that(
    happens: Callable[[], None], world: Served, plan: Path, out: Path
) -> subprocess.CompletedProcess:
    """``run`` with an operator who moves the machine where told; at the fifth prompt,
    ``happens()`` first (a Ctrl-C, a pulled cable)."""

    def at_the_fifth_prompt(n: int) -> None:
        if n == 5:
            happens()

    return _run(Terminal(moving_operator(world.machine, at_the_fifth_prompt)), world, plan, out)


def _presses_ctrl_c() -> None:
    raise KeyboardInterrupt


def test_live_run_stepped_by_the_operator_captures_every_point(
    reference_machine, short_plan, tmp_path
):
    out = tmp_path / "m.csv"
    with served(reference_machine, tmp_path, short_plan) as world:
        terminal = Terminal(moving_operator(world.machine))
        result = _run(terminal, world, short_plan, out, "--log-file", str(tmp_path / "wire.log"))
        assert result.returncode == 0, result.stderr + result.stdout
        assert all(axis.is_locked() for axis in world.axes())
    points = _points(short_plan)
    assert _keys(out) == points
    assert f"{len(points)} points captured; {len(points)} points in {out}" in result.stdout
    assert "write axis1.control" in (tmp_path / "wire.log").read_text()


def test_live_run_stopped_by_ctrl_c_keeps_its_points_and_resumes_without_a_repeat(
    reference_machine, short_plan, tmp_path
):
    out = tmp_path / "m.csv"
    with served(reference_machine, tmp_path, short_plan) as world:
        stopped = _run_with_a_fifth_prompt_that(_presses_ctrl_c, world, short_plan, out)
        assert stopped.returncode == 130, stopped.stderr
        saved = len(read_measurements(out))
        assert 0 < saved < len(_points(short_plan))
        assert stopped.stderr.strip().splitlines() == [
            f"xmalign: stopped: {saved} points kept in {out}; go on with --resume"
        ]
        assert all(axis.is_locked() for axis in world.axes())
        resumed = _run(Terminal(moving_operator(world.machine)), world, short_plan, out, "--resume")
        assert resumed.returncode == 0, resumed.stderr
    assert _keys(out) == _points(short_plan)
    total = len(_points(short_plan))
    assert f"{total - saved} points captured; {total} points in {out}" in resumed.stdout
    assert "setup kept" in resumed.stdout or "aligned again" in resumed.stdout


@pytest.mark.parametrize("stop", [signal.SIGTERM, signal.SIGHUP], ids=lambda s: s.name)
def test_live_run_stopped_by_sigterm_or_sighup_is_handled_as_ctrl_c(
    reference_machine, short_plan, tmp_path, stop
):
    """A shutdown or a closed ssh session: units locked, every point kept, one line naming
    the signal, exit code 128 + the signal's number (143, 129), as shells report it."""
    out = tmp_path / "m.csv"
    handler = signal.getsignal(stop)
    with served(reference_machine, tmp_path, short_plan) as world:
        stopped = _run_with_a_fifth_prompt_that(
            lambda: signal.raise_signal(stop), world, short_plan, out
        )
        assert stopped.returncode == 128 + stop, stopped.stderr
        assert all(axis.is_locked() for axis in world.axes())
    saved = len(read_measurements(out))
    assert 0 < saved < len(_points(short_plan))
    assert stopped.stderr.strip().splitlines() == [
        f"xmalign: {stop.name}: stopped: {saved} points kept in {out}; go on with --resume"
    ]
    assert signal.getsignal(stop) == handler  # the command gives the signal back


def test_the_interferometer_gone_mid_run_is_one_line_and_keeps_the_points(
    reference_machine, short_plan, tmp_path
):
    out = tmp_path / "m.csv"
    with served(reference_machine, tmp_path, short_plan) as world:
        result = _run_with_a_fifth_prompt_that(world.interferometer.stop, world, short_plan, out)
        assert all(axis.is_locked() for axis in world.axes())
    saved = len(read_measurements(out))
    assert 0 < saved < len(_points(short_plan))
    assert_one_line_error(result, "interferometer", f"{saved} points kept in {out}")


def test_a_unit_server_gone_mid_run_is_said_after_the_last_point(
    reference_machine, short_plan, tmp_path
):
    """The units are locked while the machine steps: a unit lost then costs no point,
    but its axes cannot be locked at the end, and the run says so."""
    out = tmp_path / "m.csv"
    with served(reference_machine, tmp_path, short_plan) as world:
        result = _run_with_a_fifth_prompt_that(world.launch.stop, world, short_plan, out)
    assert _keys(out) == _points(short_plan)
    assert_one_line_error(
        result,
        "could not lock axes a1, a2 of the launch unit",
        f"{len(_points(short_plan))} points kept in {out}",
    )


def test_live_run_refuses_an_unreachable_unit_before_creating_the_file(short_plan, tmp_path):
    config = tmp_path / "units.yaml"
    config.write_text(
        textwrap.dedent(f"""\
        format: xmalign.units/1
        launch: {{transport: modbus-tcp, host: 127.0.0.1, port: {free_port()}}}
        receiver: {{transport: modbus-tcp, host: 127.0.0.1, port: {free_port()}}}
        interferometer: {{port: {tmp_path / "no-tty"}}}
        timeouts: {{io_s: 0.2, move_s: 1.0}}
        """)
    )
    out = tmp_path / "m.csv"
    result = xmalign(
        Terminal(lambda printed: None),
        "run",
        "--plan",
        str(short_plan),
        "--config",
        str(config),
        "--out",
        str(out),
    )
    assert_one_line_error(result, "launch unit")
    assert not out.exists()


def scripted(*lines: str | None) -> Callable[[str], str | None]:
    """An operator who types ``lines`` in turn, whatever is shown (None: end of input)."""
    answers = iter(lines)
    return lambda printed: next(answers)


def _at_line_start(short_plan: Path) -> dict:
    line = read_plan(short_plan).lines[0]
    return {
        "position_mm": line.target_points_mm()[0],
        "distance_mm": str(line.extra["beam_distance_mm"][0]),
    }


def test_align_live_manual_jogs_out_of_range_and_back_then_fine_aligns(
    reference_machine, short_plan, tmp_path
):
    start = _at_line_start(short_plan)
    with served(reference_machine, tmp_path, short_plan, start["position_mm"]) as world:
        terminal = Terminal(scripted("hello", "a2 150", "a2 -0.5", "", "a2 0.5", ""))
        result = xmalign(
            terminal,
            "align", "--live", "--manual", "--config", str(world.config),
            "--distance-mm", start["distance_mm"],
        )  # fmt: skip
        assert result.returncode == 0, result.stderr
        assert all(axis.is_locked() for axis in world.axes())
    assert terminal.prompts == 6
    shown = " ".join(result.stdout.split())  # rich wraps at the terminal width
    assert "jog command 'hello': expected an axis a1..a5" in shown
    assert "axis a2 of the launch unit at 127.0.0.1" in shown and "out of its range" in shown
    times = [float(t) for t in re.findall(r"^│ +(-?[\d.]+) │", result.stdout, re.M)]
    assert times[0] == 0.0 and times == sorted(times) and times[-1] < 10.0  # s since the first
    assert "beam out of range" in shown and "the beam is not in range yet" in shown
    assert re.search(r"beam in range: sv \d+%", shown)
    assert "s of wall time" in shown and "units locked" in shown
    cells = r" +([-+]?[\d.]+) │"
    rows = re.findall(r"^│" + cells * 7, result.stdout, re.M)
    sv, sw, aw, av, au = (float(v) for v in rows[-1][1:6])  # um, urad
    # the receiver faces the beam (the launch unit does not steer: FineAlignmentSettings)
    assert abs(sw) <= 1.0 and abs(av) <= 3.0 and abs(au) <= 3.0, rows[-1]


def test_align_live_manual_without_an_operator_is_one_line_and_locks_the_units(
    reference_machine, short_plan, tmp_path
):
    start = _at_line_start(short_plan)
    with served(reference_machine, tmp_path, short_plan, start["position_mm"]) as world:
        result = xmalign(
            Terminal(scripted("a1 0.01", None)),
            "align", "--live", "--manual", "--config", str(world.config),
        )  # fmt: skip
        assert all(axis.is_locked() for axis in world.axes())
    assert_one_line_error(result, "no answer from the operator (end of input)")


class IdentifyingOperator:
    """At the terminal during ``identify --live``: moves the machine where told, and at the
    jog prompt jogs each axis to where the beam passes (what a person watching the
    receiver's range display achieves, here from the simulator's truth), then Enter."""

    def __init__(self, world: Served, machine, ctrl_c_at_move: int | None = None) -> None:
        self.world = world
        self.machine = machine
        self.ctrl_c_at_move = ctrl_c_at_move
        self.moves = 0
        self.manual = 0
        self.jogs: list[str] = []

    def __call__(self, printed: str) -> str | None:
        if printed.rstrip().endswith("jog>"):
            if "Jog: 'a<n> <deg>'" in printed:
                self.manual += 1
                self.jogs = self._jogs_to_the_beam()
            return self.jogs.pop(0) if self.jogs else ""
        moves = MOVE.findall(printed)
        assert moves, f"asked without a move: {printed!r}"
        self.moves += 1
        if self.moves == self.ctrl_c_at_move:
            raise KeyboardInterrupt
        self.world.machine.position = np.array([float(v) for v in moves[-1]])
        return ""

    def _jogs_to_the_beam(self) -> list[str]:
        from sim.alignment_setup import point_by_truth
        from sim.units import SimPositioningUnit
        from sim.world import World

        truth: World = self.world.setup.world
        launch, receiver = SimPositioningUnit(truth.launch), SimPositioningUnit(truth.receiver)
        now_rad = np.concatenate([launch.angles_rad(), receiver.angles_rad()])
        planner = _AngleRecorder()
        point_by_truth(truth, self.machine, planner.launch, planner.receiver)
        steps_deg = np.degrees(np.concatenate(planner.targets) - now_rad)
        return [f"a{n} {step:.7f}" for n, step in enumerate(steps_deg, start=1) if step]


class _AngleRecorder:
    """Stands in for both units to learn the angles point_by_truth would command."""

    def __init__(self) -> None:
        self.targets: list[np.ndarray] = []
        recorder = self

        class _Unit:
            def move_to(self, angles_rad, timeout_s: float) -> None:
                recorder.targets.append(np.asarray(angles_rad, dtype=float))

        self.launch, self.receiver = _Unit(), _Unit()


def _identify(terminal: Terminal, world: Served, session: Path, *extra: str):
    return xmalign(
        terminal,
        "identify", "--live", "--config", str(world.config), "--session", str(session),
        "--alignments", "3", *extra,
    )  # fmt: skip


def test_identify_live_searching_the_first_beam_then_resumed_after_ctrl_c(
    reference_machine, tmp_path
):
    """No azimuth in the machine file and the launch unit 28 mm from its place there
    (seed 3, 201 mm from the first position): the first alignment is the search's;
    Ctrl-C at the second position, then the routine resumes and points positions 2 and
    3 from the first alignment's beam line, searching along it: no one jogs, before or
    after Ctrl-C."""
    session, pose = tmp_path / "session.json", tmp_path / "pose.json"
    with served(reference_machine, tmp_path) as world:
        first = IdentifyingOperator(world, reference_machine, ctrl_c_at_move=2)
        stopped = _identify(Terminal(first), world, session)
        assert stopped.returncode == 130, stopped.stderr
        assert all(axis.is_locked() for axis in world.axes())
        assert len(json.loads(session.read_text())["alignments"]) == 1
        assert first.manual == 0  # no azimuth guess: the first alignment is the search's
        assert "position 1: searching the beam" in " ".join(stopped.stdout.split())
        second = IdentifyingOperator(world, reference_machine)
        result = _identify(Terminal(second), world, session, "--out", str(pose))
        assert result.returncode == 0, result.stderr
        assert all(axis.is_locked() for axis in world.axes())
        truth = world.setup.world
    assert second.moves == 2  # the recorded alignment is not repeated
    assert second.manual == 0  # positions 2 and 3 pointed from the beam line, no jog
    assert len(json.loads(session.read_text())["alignments"]) == 3
    shown = " ".join(result.stdout.split())
    assert "Launch-unit pose (joint, 3 of 3 alignments" in shown
    assert f"pose written to {pose}".replace(" ", "") in "".join(shown.split())  # wrapped
    identified = read_pose(pose)
    sigma = np.sqrt(np.diag(identified.covariance))
    error = np.append(
        identified.position_mm - truth.launch2mcs_mm,
        math.remainder(identified.gamma_rad - truth.gamma_rad, math.tau),
    )
    assert np.all(np.abs(error) < 3 * sigma), (error, sigma)  # within its own uncertainty


def test_identify_live_without_a_launch_place_is_refused_before_anything_moves(
    reference_machine, reference_machine_path, tmp_path
):
    """A machine file without ``launch_unit``: nothing to search from, and identify
    --live says so in one line (no jog of the first alignment, no session)."""
    import yaml

    data = yaml.safe_load(reference_machine_path.read_text())
    del data["launch_unit"]
    machine_file = tmp_path / "no-launch-place.yaml"
    machine_file.write_text(yaml.safe_dump(data))
    session = tmp_path / "session.json"
    with served(reference_machine, tmp_path) as world:
        operator = IdentifyingOperator(world, reference_machine)
        result = _identify(Terminal(operator), world, session, "--machine", str(machine_file))
    assert_one_line_error(result, "no launch_unit.position_mm")
    assert operator.moves == 0 and operator.manual == 0
    assert not session.exists()


def _rows_in(path: Path) -> int:
    """Data rows written so far (read while the run writes)."""
    if not path.exists():
        return 0
    lines = path.read_bytes().split(b"\n")[:-1]  # a row counts once its newline is there
    return sum(1 for line in lines if line and not line.startswith((b"#", b"line,")))


@pytest.fixture
def two_short_lines(plans, tmp_path):
    """Lines Z and X, each cut to three targets, one bidirectional run, short dwell."""
    data = json.loads((plans / "plan.json").read_text())
    for line in data["lines"]:
        line.update(targets_mm=line["targets_mm"][:3], runs=1, bidirectional=True, dwell_s=0.1)
    path = tmp_path / "plan.json"
    path.write_text(json.dumps(data))
    return path


@contextlib.contextmanager
def controller_running_the_plan(
    world: Served,
    terminal: Terminal,
    plan_path: Path,
    overrun_mm: float,
    out: Path,
    report: Callable[[np.ndarray], None],
    cycle_start: Callable[[], None] | None = None,
) -> Iterator[None]:
    """A script in a thread of its own that runs the program as a controller would, while
    the ``with`` block runs xmalign; ``report(point_mm)`` publishes where the machine stands
    (a position file, an agent, an OPC UA server) as the interferometer sees it there.

    First, with ``cycle_start``, it waits for xmalign to say "press Cycle Start" and calls
    it. Then to each line's pre-position, where it stops until cycle start (the run sets
    the units there), then to each target in turn, going on once the point is in the
    measurement file; where the program stops twice at one place (end of a run and start
    of the way back, the drift check), it moves away and back first, as the program's
    overrun does. Between lines it travels (retract and approach): the run must not set
    the units for the next line before the machine stands at its pre-position.
    """
    lines = read_plan(plan_path).lines
    pre_positions = [line.target_points_mm()[0] - overrun_mm * line.frame[0] for line in lines]
    stop = threading.Event()

    def stand_at(point_mm: np.ndarray) -> None:
        world.machine.position = np.asarray(point_mm)
        report(np.asarray(point_mm))

    def said(text: str) -> None:
        while text not in terminal.out.getvalue() and not stop.wait(0.01):
            pass

    def controller() -> None:
        if cycle_start is not None:
            said("press Cycle Start")
            cycle_start()
        captured = 0
        for number, (line, pre_mm) in enumerate(zip(lines, pre_positions, strict=True)):
            if number:  # the retract and approach: a while, and the units stay locked
                stand_at((pre_positions[number - 1] + pre_mm) / 2)
                stop.wait(1.0)
                while not all(a.is_locked() for a in world.axes()) and not stop.wait(0.01):
                    pass
            stand_at(pre_mm)  # M0: cycle start once the units are set
            said(f"line {line.id}: units aligned and locked; press cycle start")
            points = [p.point_mm for p in capture_sequence(line)]
            for k, point_mm in enumerate(points):
                if k and np.allclose(point_mm, points[k - 1]):
                    stand_at(np.asarray(point_mm) + 2.0)  # the overrun
                    stop.wait(0.3)  # the run polls every 0.05 s
                stand_at(point_mm)
                captured += 1
                while _rows_in(out) < captured and not stop.wait(0.01):
                    pass

    thread = threading.Thread(target=controller, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(timeout=5)


def pre_position(reference_machine, plan_path: Path) -> np.ndarray:  # noqa: ANN001
    """Where the program stops before the plan's first line."""
    line = read_plan(plan_path).lines[0]
    return line.target_points_mm()[0] - reference_machine.measurement.overrun_mm * line.frame[0]


def test_live_run_follows_a_machine_that_reports_its_position_in_a_file(
    reference_machine, two_short_lines, tmp_path
):
    """machine_position source: file, the machine a script that runs the program."""
    out, position_file = tmp_path / "m.csv", tmp_path / "position.txt"
    terminal = Terminal(lambda printed: None)
    start_mm = pre_position(reference_machine, two_short_lines)
    with served(reference_machine, tmp_path, two_short_lines, start_mm) as world:
        world.config.write_text(
            world.config.read_text()
            + f"machine_position: {{source: file, file: {position_file}}}\n"
        )

        def write_position(point_mm: np.ndarray) -> None:
            written = position_file.with_suffix(".new")  # replaced whole, never torn
            written.write_text("# X Y Z\n" + " ".join(f"{v:.4f}" for v in point_mm))
            os.replace(written, position_file)

        overrun_mm = reference_machine.measurement.overrun_mm
        with controller_running_the_plan(
            world, terminal, two_short_lines, overrun_mm, out, write_position
        ):
            result = _run(terminal, world, two_short_lines, out)
        assert result.returncode == 0, result.stderr
    assert _keys(out) == _points(two_short_lines)
    rows = read_measurements(out)
    # aligned where the plan aligned the beam: both lines well inside the straightness range
    assert max(np.abs(r.channels[1:3]).max() for r in rows) < 100.0


def test_a_program_for_more_lines_than_the_plan_is_refused_with_the_points_kept(plans, tmp_path):
    """run --sim executes the program of lines Z and X against the plan cut to line Z."""
    data = json.loads((plans / "plan.json").read_text())
    data["lines"] = data["lines"][:1]
    plan = tmp_path / "plan.json"
    plan.write_text(json.dumps(data))
    out = tmp_path / "m.csv"
    program = plans / "run.nc"
    result = xmalign(
        Terminal(lambda printed: None),
        "run", "--sim", "--in-process", "--seed", str(SEED), "--plan", str(plan), "--out", str(out),
        "--program", str(program),
    )  # fmt: skip
    kept = len(read_measurements(out))
    assert kept == len(_points(plan))  # line Z was measured before the program went on
    assert_one_line_error(
        result, "the program stops for more lines than the plan has", f"{kept} points kept"
    )


def test_a_live_resume_of_a_file_recorded_with_the_environment_needs_the_same_source(
    reference_machine, short_plan, tmp_path
):
    out = tmp_path / "m.csv"
    recorded = xmalign(
        Terminal(lambda printed: None),
        "run", "--sim", "--in-process", "--seed", str(SEED), "--plan", str(short_plan),
        "--out", str(out),
    )  # fmt: skip
    assert recorded.returncode == 0, recorded.stderr
    before = out.read_bytes()
    with served(reference_machine, tmp_path, short_plan) as world:
        result = _run(Terminal(lambda printed: None), world, short_plan, out, "--resume")
    assert_one_line_error(
        result, str(out), "was recorded with the environment", "same environment source"
    )
    assert out.read_bytes() == before
