"""The served world: host and servers in lockstep on one virtual clock, over the real protocols."""

import dataclasses
import inspect
import threading
import time

import numpy as np
import pytest
from cli_helpers import run_cli

import sim.servers.modbus as modbus_server
from firmware_iface.config import Timeouts
from sim.clock import LockstepClock
from sim.dry_run import measure_controlled, measure_served, measure_virtually, virtual_setup
from sim.servers.linuxcncrsh import LinuxcncrshServer
from sim.servers.serial_pty import PtyInterferometerServer
from trajectories.gcode import DIALECTS
from trajectories.gcode.program import write_program
from xmalign.calibration import capture_sequence, open_run_output
from xmalign.formats.measurements import (
    RUN_START_TAG,
    plan_sha256,
    read_measurements,
    write_measurements,
)
from xmalign.formats.plan import read_plan, write_plan

SEED = 3


def test_a_follower_runs_at_its_own_virtual_time_and_timers_on_theirs():
    clock = LockstepClock()
    woke_at: list[float] = []
    beats: list[float] = []

    def program() -> None:
        for _ in range(3):
            clock.sleep(0.7)
            woke_at.append(clock.now())
        clock.wait_for_resume()
        woke_at.append(clock.now())

    follower = clock.start_follower(program, "program")
    clock.call_every(0.5, lambda: beats.append(clock.now()))
    clock.sleep(1.0)
    assert woke_at == pytest.approx([0.7]) and beats == pytest.approx([0.5, 1.0])
    clock.sleep(2.0)  # the follower then waits for a resume: time goes on without it
    assert woke_at == pytest.approx([0.7, 1.4, 2.1]) and clock.now() == pytest.approx(3.0)
    clock.resume(follower)
    assert woke_at[-1] == pytest.approx(3.0) and follower.done


def test_a_released_follower_runs_to_its_end_without_time_passing():
    clock = LockstepClock()
    ended = threading.Event()

    def program() -> None:
        clock.sleep(100.0)
        clock.wait_for_resume()
        ended.set()

    follower = clock.start_follower(program, "program")
    clock.release(follower)
    assert ended.wait(5.0) and clock.now() == 0.0


@pytest.fixture(scope="module")
def short_plan(dry_run_of_seed, reference_machine, tmp_path_factory):
    """The dry run's lines Z and X cut to three targets and one run (7 points each)."""
    workdir = tmp_path_factory.mktemp("served")
    plan = read_plan(dry_run_of_seed(SEED, "served")[1] / "plan.json")
    lines = []
    for line in (plan.line("Z"), plan.line("X")):
        length_mm = float(line.targets_mm[2])
        lines.append(
            dataclasses.replace(
                line,
                targets_mm=line.targets_mm[:3],
                end_mm=line.start_mm + length_mm * line.frame[0],
                runs=1,
                extra={**line.extra, "length_mm": length_mm},
            )
        )
    write_plan(workdir / "plan.json", dataclasses.replace(plan, lines=lines))
    return workdir / "plan.json"


def _measure(machine, plan_path, path, served, rows=None):
    plan = read_plan(plan_path)
    program = write_program(plan, machine, DIALECTS["linuxcnc"]())
    if rows is not None:
        write_measurements(path, rows, plan_sha256(plan))
    setup = virtual_setup(machine, SEED, lockstep=served)
    with open_run_output(path, plan, resume=rows is not None) as output:
        if served:
            run = measure_served(setup, machine, plan, program, "linuxcnc", output)
        else:
            run = measure_virtually(setup, plan, program, "linuxcnc", output)
    return run, read_measurements(path)


def _assert_close(served, in_process):
    assert [r.key() for r in served] == [r.key() for r in in_process]
    pairs = zip(served, in_process, strict=True)
    difference = np.array([a.channels - b.channels for a, b in pairs])
    # the same world measured the same way; only the noise draws and the alignment's end differ,
    # and the datum: the live run zeroes when the position file shows the machine within 5 µm
    # of the run's first target, the program's dwell event when it stands (one constant per
    # run, which post fits)
    runs = [(r.line, r.run) for r in served]
    for run in set(runs):
        linear = difference[[k for k, key in enumerate(runs) if key == run], 0]
        # single points differ by up to 1.2 µm between the paths (seen at a run's first target
        # and the drift check; not explained yet, docs/simulator.md)
        assert np.abs(linear - linear.mean()).max() < 2.0  # µm
        assert abs(linear.mean()) < 6.0
    assert np.abs(difference[:, 1:3]).max() < 15.0  # straightness, µm
    assert np.abs(difference[:, 3:]).max() < 15.0  # angles, µrad


def test_served_run_captures_what_the_in_process_run_captures(
    reference_machine, short_plan, tmp_path
):
    served_run, served = _measure(reference_machine, short_plan, tmp_path / "s.csv", True)
    _, in_process = _measure(reference_machine, short_plan, tmp_path / "i.csv", False)
    _assert_close(served, in_process)
    assert served_run.statistics.points == 14 and not served_run.statistics.missed
    assert list(served_run.statistics.alignments) == ["Z", "X"]


def test_served_run_resumes_after_the_lines_it_has(reference_machine, short_plan, tmp_path):
    _, full = _measure(reference_machine, short_plan, tmp_path / "full.csv", False)
    run, resumed = _measure(reference_machine, short_plan, tmp_path / "r.csv", True, full[:9])
    assert [r.key() for r in resumed] == [r.key() for r in full]
    assert run.statistics.points == 5 and list(run.statistics.alignments) == ["X"]
    plan = read_plan(short_plan)
    assert len(resumed) == sum(1 for line in plan.lines for _ in capture_sequence(line))


def test_run_sim_is_served_by_default(short_plan, tmp_path):
    """``run --sim`` goes over the protocols unless told ``--in-process`` (the in-process
    path: tests/xmalign/test_cli_run.py): the wire log shows Modbus and the serial line."""
    out, wire = tmp_path / "served.csv", tmp_path / "wire.log"
    result = run_cli(
        "run", "--sim", "--seed", str(SEED), "--plan", str(short_plan), "--out", str(out),
        "--log-file", str(wire),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert "14 points captured" in result.stdout
    logged = wire.read_text()
    assert "write axis1.control" in logged and "STREAM ON" in logged
    assert len(read_measurements(out)) == 14


def test_a_controlled_run_over_linuxcncrsh_captures_what_the_in_process_run_captures(
    reference_machine, short_plan, tmp_path, monkeypatch
):
    """The dry run's path: xmalign starts, resumes (and would hold) the program on a
    simulated LinuxCNC over linuxcncrsh, all on the world's virtual clock; wired by the step
    ``xmalign run --config`` calls too (tests/xmalign/test_one_pipeline.py)."""
    import sim.dry_run as dry_run
    from xmalign import steps

    calls = []

    def spy(*args, **kwargs):
        calls.append(args)
        return steps.controlled_run_step(*args, **kwargs)

    monkeypatch.setattr(dry_run, "controlled_run_step", spy)
    plan = read_plan(short_plan)
    setup = virtual_setup(reference_machine, SEED, lockstep=True)
    with open_run_output(tmp_path / "c.csv", plan, resume=False) as output:
        run = measure_controlled(setup, reference_machine, plan, output)
    controlled = read_measurements(tmp_path / "c.csv")
    _, in_process = _measure(reference_machine, short_plan, tmp_path / "i.csv", False)
    _assert_close(controlled, in_process)
    assert run.statistics.points == 14 and not run.statistics.missed
    assert run.statistics.program_s is not None and run.statistics.program_s > 0
    assert len(calls) == 1


def _measured_lines(path):
    """The measurement file's lines but those that say when it was written."""
    lines = path.read_text(encoding="utf-8").splitlines()
    return [line for line in lines if not line.startswith(("# created_utc:", RUN_START_TAG))]


#: A server thread held this long (wall clock): longer than the default ``timeouts.io_s``.
LATE_S = Timeouts().io_s + 0.5


def _late(monkeypatch, owner, name, nth):
    """``owner.name`` (a server's reply) held :data:`LATE_S` at its ``nth`` call: the
    schedule of a busy computer, where a server's thread gets the CPU a second late."""
    original = getattr(owner, name)
    calls = iter(range(1, 10**9))

    def hold() -> None:
        if next(calls) == nth:
            time.sleep(LATE_S)

    if inspect.iscoroutinefunction(original):

        async def late_async(*args, **kwargs):
            hold()
            return await original(*args, **kwargs)

        monkeypatch.setattr(owner, name, late_async)
    else:

        def late(*args, **kwargs):
            hold()
            return original(*args, **kwargs)

        monkeypatch.setattr(owner, name, late)


@pytest.mark.parametrize("path", ["controlled", "position-file"])
def test_a_served_run_is_repeatable_to_the_last_digit(
    reference_machine, short_plan, tmp_path, monkeypatch, path
):
    """Two served runs of one seed write the same file, however the threads of the host and
    the servers are scheduled (the host's waits for streamed samples go through its clock,
    docs/simulator.md); the dry run's path (LinuxCNC) and ``run --sim``'s (position file).

    The second run has a Modbus reply, an interferometer sample and (LinuxCNC) a
    linuxcncrsh reply each come 1.5 s late. Issue 32: under load the first run's
    host took such a late Modbus reply for a lost one (the 1 s ``io_s``) and sent the
    request again: the alignment and every reading differed (a late sample or
    linuxcncrsh reply failed the run)."""
    plan = read_plan(short_plan)
    program = write_program(plan, reference_machine, DIALECTS["linuxcnc"]())
    files = []
    for name in ("first.csv", "second.csv"):
        if name == "second.csv":
            _late(monkeypatch, modbus_server._Handler, "_answer", 200)
            _late(monkeypatch, PtyInterferometerServer, "_send", 50)
            _late(monkeypatch, LinuxcncrshServer, "_answer", 30)
        setup = virtual_setup(reference_machine, SEED, lockstep=True)
        with open_run_output(tmp_path / name, plan, resume=False) as output:
            if path == "controlled":
                measure_controlled(setup, reference_machine, plan, output)
            else:
                measure_served(setup, reference_machine, plan, program, "linuxcnc", output)
        files.append(_measured_lines(tmp_path / name))
    assert len(read_measurements(tmp_path / "first.csv")) == 14
    assert files[0] == files[1]
