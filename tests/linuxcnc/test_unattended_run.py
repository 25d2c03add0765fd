"""``xmalign run`` with no one at the machine: a real headless LinuxCNC runs xmalign's program.

LinuxCNC 2.9 (Debian ``linuxcnc-uspace``) runs with ``linuxcncrsh`` as its
display (tests/linuxcnc/harness.py); the test plays the operator only to bring
the machine up (E-stop reset, machine on, home), over a linuxcncrsh session of
its own. ``xmalign sim serve`` serves both units and the interferometer, and
its virtual machine carries the receiver where LinuxCNC says the machine is:
``xmalign sim publish-position`` keeps LinuxCNC's actual position in a file
(``linuxcnc.stat().actual_position``, the quantity of linuxcncrsh's
``abs_act_pos``) and ``sim serve --follow-position-file`` follows it. (Not a
second linuxcncrsh session: linuxcncrsh 2.9 garbles commands of concurrent
sessions; docs/hardware.md.) ``xmalign run --config`` then writes its program,
starts it, sets the units at each line's stop, captures at each point's stop
and resumes, to the program's end.

The plans are the reference machine's lines at 20 m/min from ``xmalign program
--max-length-mm 20`` with targets 10 mm apart (three targets, one run each way):
all six lines, three axes and three face diagonals, for one complete unattended
calibration (about two minutes of real time), and lines Z and X for the beam
lost, the pulled cable and the wrong program.
"""

from __future__ import annotations

import dataclasses
import re
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import Process, free_port
from harness import SimMachine, bring_up, linuxcnc_publishing, write_sim_config
from test_real_faults import kill_milltask, press_estop

from firmware_iface.linuxcncrsh import open_linuxcnc
from tests.xmalign.test_live_e2e import GAMMA_DEG, SEED, try_out_plan
from trajectories.gcode import make_dialect
from trajectories.gcode.program import write_program
from xmalign.calibration import capture_sequence
from xmalign.formats.measurements import load_measurements
from xmalign.formats.plan import read_plan
from xmalign.machine import load_machine

pytestmark = pytest.mark.linuxcnc

LINES = ("Z", "X")


@pytest.fixture(scope="module")
def short_plan(tmp_path_factory: pytest.TempPathFactory, reference_machine_path: Path) -> Path:
    """Lines Z and X (see :func:`try_out_plan`)."""
    return try_out_plan(tmp_path_factory.mktemp("plan"), reference_machine_path, LINES)


@pytest.fixture(scope="module")
def six_line_plan(tmp_path_factory: pytest.TempPathFactory, reference_machine_path: Path) -> Path:
    """All six lines: the three axes and the three face diagonals (see :func:`try_out_plan`)."""
    return try_out_plan(tmp_path_factory.mktemp("six"), reference_machine_path, ())


class CablePuller:
    """A TCP relay between xmalign and linuxcncrsh whose cable the test can pull and plug."""

    def __init__(self, target_port: int) -> None:
        self.port = free_port()
        self.target_port = target_port
        self._connections: list[socket.socket] = []
        self._listener: socket.socket | None = None
        self.plug()

    def plug(self) -> None:
        listener = socket.socket()
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(("127.0.0.1", self.port))
        listener.listen()
        self._listener = listener
        threading.Thread(target=self._accept, args=(listener,), daemon=True).start()

    def pull(self) -> None:
        """Every connection cut, none accepted until :meth:`plug`."""
        if self._listener is not None:
            with suppress(OSError):
                self._listener.shutdown(socket.SHUT_RDWR)  # wakes the thread in accept()
            self._listener.close()
            self._listener = None
        for connection in self._connections:
            with suppress(OSError):
                connection.shutdown(socket.SHUT_RDWR)
            connection.close()
        self._connections.clear()

    def _accept(self, listener: socket.socket) -> None:
        while True:
            try:
                client, _ = listener.accept()
            except OSError:
                return
            server = socket.create_connection(("127.0.0.1", self.target_port))
            self._connections += [client, server]
            for a, b in ((client, server), (server, client)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    @staticmethod
    def _pump(source: socket.socket, sink: socket.socket) -> None:
        with suppress(OSError):
            while data := source.recv(4096):
                sink.sendall(data)
        with suppress(OSError):
            sink.shutdown(socket.SHUT_RDWR)


#: How xmalign reaches LinuxCNC in units.yaml (``source``: the keys before ``program``).
_CHANNELS = {"linuxcncrsh": "host: 127.0.0.1, port: {port}, ", "linuxcnc": ""}


class Shop:
    """LinuxCNC (brought up by the 'operator'), ``sim serve`` following it, a units.yaml
    whose ``source`` (linuxcncrsh, or linuxcnc: the Python module) xmalign reaches it by."""

    def __init__(
        self, workdir: Path, rsh_port: int, position_file: Path, source: str = "linuxcncrsh"
    ) -> None:
        self.workdir = workdir
        self.cable = CablePuller(rsh_port)
        operator = open_linuxcnc("127.0.0.1", rsh_port, 5.0)
        bring_up(operator)
        operator.close()
        ports = [free_port(), free_port()]
        args = ["sim", "serve", "--seed", str(SEED), "--gamma-deg", str(GAMMA_DEG)]
        args += ["--modbus", str(ports[0]), "--modbus-receiver", str(ports[1])]
        args += ["--interferometer-pty", "--machine", "machine.yaml"]
        args += ["--follow-position-file", str(position_file)]
        self.server = Process(args, workdir, stdin=subprocess.PIPE)
        pty = self.server.wait_for("interferometer on").split()[-1]
        self.server.wait_for("serving")
        (workdir / "units.yaml").write_text(
            "format: xmalign.units/1\n"
            f"launch: {{transport: modbus-tcp, host: 127.0.0.1, port: {ports[0]}}}\n"
            f"receiver: {{transport: modbus-tcp, host: 127.0.0.1, port: {ports[1]}}}\n"
            f"interferometer: {{port: {pty}, rate_hz: 50}}\n"
            "machine_position:\n"
            f"  source: {source}\n"
            f"  {source}: {{{_CHANNELS[source].format(port=self.cable.port)}program: run.ngc}}\n"
            "timeouts: {io_s: 2.0, move_s: 30.0, machine_s: 120.0}\n"
        )

    def block_beam(self, seconds: float) -> None:
        stdin = self.server.popen.stdin
        assert stdin is not None
        stdin.write(f"block-beam {seconds}\n")
        stdin.flush()

    def program_state(self) -> str:
        """What LinuxCNC says about the program, asked over a session of the test's own."""
        cnc = open_linuxcnc("127.0.0.1", self.cable.target_port, 5.0, enable_password=None)
        try:
            return cnc.program_state()
        finally:
            cnc.close()

    def run(self, *extra: str) -> Process:
        return Process(
            ["run", "--config", "units.yaml", "--machine", "machine.yaml", "--plan", "plan.json"]
            + ["--out", "m.csv", "--log-file", "wire.log", *extra],
            self.workdir,
        )


@contextmanager
def shop_running(plan_dir: Path, linuxcnc_dir: Path, source: str = "linuxcncrsh") -> Iterator[Shop]:
    machine = load_machine(plan_dir / "machine.yaml")
    for name in ("machine.yaml", "plan.json"):
        (linuxcnc_dir / name).write_bytes((plan_dir / name).read_bytes())
    port = free_port()
    travel = {
        axis: (float(low), float(high))
        for axis, low, high in zip("XYZ", machine.travel_min_mm, machine.travel_max_mm, strict=True)
    }
    cnc = SimMachine(
        travel_mm=travel,
        max_velocity_mm_s=machine.feed_mm_min.rapid / 60.0,
        max_acceleration_mm_s2=float(machine.cnc.acceleration_mm_s2 or 5000.0),
    )
    position_file = linuxcnc_dir / "cnc" / "position.txt"
    ini = write_sim_config(linuxcnc_dir / "cnc", cnc, f"linuxcncrsh --port {port}")
    with linuxcnc_publishing(ini, port, position_file):
        served = Shop(linuxcnc_dir, port, position_file, source)
        try:
            yield served
        finally:
            served.server.stop()
            served.cable.pull()


@pytest.fixture
def shop(short_plan: Path, linuxcnc_dir: Path) -> Iterator[Shop]:
    with shop_running(short_plan, linuxcnc_dir) as served:
        yield served


@pytest.fixture
def six_line_shop(six_line_plan: Path, linuxcnc_dir: Path) -> Iterator[Shop]:
    with shop_running(six_line_plan, linuxcnc_dir) as served:
        yield served


def _keys(path: Path) -> list[tuple]:
    return [(r.line, r.run, r.direction, r.index) for r in load_measurements(path).rows]


def _expected_keys(plan_path: Path) -> list[tuple]:
    return [p.key for line in read_plan(plan_path).lines for p in capture_sequence(line)]


def _wait_for_rows(run: Process, path: Path, count: int, timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and run.popen.poll() is None:
        if path.exists() and len(load_measurements(path, torn_ok=True).rows) >= count:
            return
        time.sleep(0.02)
    raise AssertionError(f"{path} holds fewer than {count} points:\n{run.said()}")


_STAMP = re.compile(r"^(\S+)Z .* > '(set (?:pause|resume))'")


def _holds_s(wire_log: str) -> list[float]:
    """How long each feed hold (``set pause`` to the next ``set resume``) lasted, s."""
    held, holds = None, []
    for line in wire_log.splitlines():
        match = _STAMP.match(line)
        if match is None:
            continue
        when = datetime.fromisoformat(match.group(1)).timestamp()
        if match.group(2) == "set pause":
            held = when
        elif held is not None:
            holds.append(when - held)
            held = None
    return holds


def test_unattended_run_on_linuxcnc_with_the_beam_lost_and_found(shop: Shop) -> None:
    run = shop.run()
    _wait_for_rows(run, shop.workdir / "m.csv", 3)
    shop.block_beam(1.0)
    assert run.finish(timeout_s=300) == 0, run.said()
    assert _keys(shop.workdir / "m.csv") == _expected_keys(shop.workdir / "plan.json")
    said = run.said()
    points = len(_expected_keys(shop.workdir / "plan.json"))
    assert f"{points} points captured; {points} points in m.csv" in said
    assert "found again" in said or "feed held" in said, said
    rows = load_measurements(shop.workdir / "m.csv").rows
    # each captured with the machine at rest where the plan says: some µm over 20 mm
    assert max(abs(r.channels[0]) for r in rows) < 20.0
    assert max(np.abs(r.channels[1:3]).max() for r in rows) < 100.0
    assert "machine time" in said and "G-code estimate" in said
    wire = (shop.workdir / "wire.log").read_text()
    assert "set enable ****" in wire and "EMCTOO" not in wire and "hello ****" in wire
    if "feed held" in said:  # lost on the way: the feed held until the beam came back
        assert max(_holds_s(wire)) > 0.5, wire
    else:  # lost at a point: the program stood at its stop through the recovery
        assert "found again after" in said
    print(*(line for line in said.splitlines() if "machine time" in line or "beam" in line))


def _machine_time_s(said: str) -> tuple[float, float]:
    """The run's machine time (without the stops for the units) and the G-code's estimate, s."""
    found = re.search(r"machine time ([\d.]+) s without .* \(G-code estimate ([\d.]+) s\)", said)
    assert found is not None, said
    return float(found[1]), float(found[2])


def test_a_pulled_cable_stops_the_run_and_resume_completes_it_at_speed(shop: Shop) -> None:
    """The cable pulled once the first line is recorded: the error says --resume; the
    resumed run passes the recorded line at once (no feed hold, no beam searched for,
    though the units are set for another line) and takes the G-code's time."""
    out = shop.workdir / "m.csv"
    first_line = len(list(capture_sequence(read_plan(shop.workdir / "plan.json").lines[0])))
    run = shop.run()
    _wait_for_rows(run, out, first_line + 1)
    shop.cable.pull()
    code = run.finish(timeout_s=60)
    assert code == 2, run.said()
    (line,) = [text for text in run.stderr.splitlines() if text.strip()]
    assert line.startswith("xmalign: error: ") and "LinuxCNC at 127.0.0.1" in line, line
    assert "could not be reached" in line and "points kept in" in line, line
    assert "--resume" in line, line
    kept = load_measurements(out, torn_ok=True).rows
    shop.cable.plug()
    resumed = shop.run("--resume")
    assert resumed.finish(timeout_s=300) == 0, resumed.said()
    said = resumed.said()
    assert "aborted, started again from the top" in said
    assert "feed held" not in said and "searched for" not in said, said
    assert _keys(out) == _expected_keys(shop.workdir / "plan.json")
    again = load_measurements(out).rows[: len(kept)]
    assert all(np.array_equal(a.channels, b.channels) for a, b in zip(again, kept, strict=True))
    machine_s, estimate_s = _machine_time_s(said)
    print(f"resumed: machine time {machine_s:.1f} s, G-code estimate {estimate_s:.1f} s")
    assert machine_s < 1.2 * estimate_s, said


def test_a_program_that_is_not_the_plans_stops_the_run_with_one_line(shop: Shop) -> None:
    """The shared folder misconfigured: LinuxCNC opens an old program whose line Z lies 1 mm
    off the plan's. The machine stops at that program's first stop; xmalign refuses to
    set the units there, stops the program and says so in one line."""
    plan = read_plan(shop.workdir / "plan.json")
    machine = load_machine(shop.workdir / "machine.yaml")
    first = plan.lines[0]
    moved = dataclasses.replace(first, start_mm=first.start_mm + np.array([1.0, 0.0, 0.0]))
    stale = shop.workdir / "cnc" / "old.ngc"
    stale.write_text(
        write_program(
            dataclasses.replace(plan, lines=[moved, *plan.lines[1:]]),
            machine,
            make_dialect("linuxcnc", machine, "old", stop_at_points=True),
        )
    )
    stale.chmod(0o644)
    config = shop.workdir / "units.yaml"
    config.write_text(
        config.read_text().replace(
            "program: run.ngc}", f"program: run.ngc, program_on_cnc: {stale}}}"
        )
    )
    run = shop.run()
    assert run.finish(timeout_s=120) == 2, run.said()
    (line,) = [text for text in run.stderr.splitlines() if text.strip()]
    assert "program and plan do not match" in line and "pre-position of line Z" in line, line
    assert "1.0000 mm from" in line and "the program was stopped on the controller" in line
    assert shop.program_state() == "idle"


def test_an_unattended_calibration_of_all_six_lines(six_line_shop: Shop) -> None:
    """All six lines with no one at the machine: xmalign starts the program, sets the units
    at each line's stop, captures at every point's stop and resumes, to the end; the time
    on the machine is the G-code's estimate plus the settling (both printed)."""
    shop = six_line_shop
    run = shop.run()
    assert run.finish(timeout_s=900) == 0, run.said()
    expected = _expected_keys(shop.workdir / "plan.json")
    assert {key[0] for key in expected} == {"X", "Y", "Z", "XY", "YZ", "XZ"}
    assert _keys(shop.workdir / "m.csv") == expected
    said = run.said()
    assert f"{len(expected)} points captured; {len(expected)} points in m.csv" in said
    assert "machine time" in said and "G-code estimate" in said
    print(*(line for line in said.splitlines() if "machine time" in line))


def _one_error_line(run: Process) -> str:
    (line,) = [text for text in run.stderr.splitlines() if text.strip()]
    assert line.startswith("xmalign: error: "), line
    return line


def test_an_e_stop_during_the_run_is_named_with_the_points_kept_and_the_way_on(
    shop: Shop,
) -> None:
    """halcmd opens the E-stop chain mid-run: one line naming the E-stop, where, the
    points kept and --resume; no 'set abort' (LinuxCNC has ended the program)."""
    out = shop.workdir / "m.csv"
    run = shop.run()
    _wait_for_rows(run, out, 3)
    press_estop()
    assert run.finish(timeout_s=60) == 2, run.said()
    line = _one_error_line(run)
    assert "E-stop is pressed; release it, switch the machine on and home it" in line, line
    assert "the program ended on the way to " in line, line
    assert "go on with --resume when the machine is back" in line, line
    assert f"{len(load_measurements(out, torn_ok=True).rows)} points kept in m.csv" in line
    assert "set abort" not in (shop.workdir / "wire.log").read_text()


def test_a_killed_task_is_named_within_seconds(shop: Shop) -> None:
    """milltask killed mid-run: linuxcncrsh goes on saying RUNNING and takes no command;
    the run ends within seconds with one line naming the task."""
    out = shop.workdir / "m.csv"
    run = shop.run()
    _wait_for_rows(run, out, 3)
    killed = time.monotonic()
    kill_milltask()
    assert run.finish(timeout_s=120) == 2, run.said()
    took_s = time.monotonic() - killed
    line = _one_error_line(run)
    assert "milltask" in line and "points kept in m.csv" in line, line
    print(f"killed task named after {took_s:.1f} s: {line}")
    assert took_s < 30.0, line


def _cross_the_beam_while_braking_for_a_point(shop: Shop, points: list[np.ndarray]) -> float:
    """Cross the beam 0.5 s once the machine, approaching a point, is 1-4 mm from it: at
    20 m/min and 1000 mm/s^2 LinuxCNC is braking for that point's stop, and xmalign's
    feed hold comes in the braking distance. Returns that distance, mm."""
    watch = open_linuxcnc("127.0.0.1", shop.cable.target_port, 5.0, enable_password=None)
    try:
        before = np.inf
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline:
            at = watch.position_mm()
            left = min(float(np.linalg.norm(at - point)) for point in points)
            if 1.0 < left < 4.0 and left < before:
                shop.block_beam(0.5)
                return left
            before = left
        raise AssertionError("the machine never approached a point")
    finally:
        watch.close()


def test_a_beam_lost_as_the_machine_brakes_for_a_point_costs_no_wait(shop: Shop) -> None:
    """LinuxCNC 2.9 takes a feed hold in the braking distance before an M0 at the M0, and
    one resume leaves the program paused there: the run captures the point there, or
    resumes again, and ends without waiting out timeouts.machine_s (120 s here)."""
    out = shop.workdir / "m.csv"
    line = read_plan(shop.workdir / "plan.json").lines[0]
    points = [point.point_mm for point in capture_sequence(line)]
    run = shop.run()
    _wait_for_rows(run, out, 2)
    started = time.monotonic()
    left_mm = _cross_the_beam_while_braking_for_a_point(shop, points)
    assert run.finish(timeout_s=100) == 0, run.said()
    said = run.said()
    ended_s = time.monotonic() - started
    print(f"beam crossed {left_mm:.1f} mm before a point; run ended {ended_s:.1f} s later")
    assert _keys(out) == _expected_keys(shop.workdir / "plan.json")
    assert "still waiting" not in said, said
    assert "beam lost on the way" in said or "found again" in said, said
    print(*(text for text in said.splitlines() if "beam" in text or "paused" in text))
