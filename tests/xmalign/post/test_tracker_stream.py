"""``xmalign import --tracker-stream``: a tracker's stream assigned to the program's paths.

The streams come from the simulator (sim.tracker_stream): the tracker's own clock
and rate, the machine file's acceleration, servo lag and correlated noise, none
of which the import is told. What it keeps is checked against the simulator's
own timeline of the program (sim.tracker_stream.program_timeline).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from cli_helpers import assert_one_line_error, run_cli, run_in_process

from sim.machine import ErrorAmplitudes, VirtualMachine
from sim.tracker import VirtualTracker
from sim.tracker_stream import StreamOptions, program_timeline, record_stream
from trajectories.instruments import InstrumentProgram, fly_paths, point_list_csv, tracker_place
from xmalign.errors import InputError
from xmalign.formats.common import atomic_write_text
from xmalign.formats.instruments import read_tracker_points
from xmalign.formats.provenance import file_sha256
from xmalign.formats.tracker_stream import StreamRun, read_tracker_stream, write_tracker_stream
from xmalign.machine import Machine, default_machine_path
from xmalign.machine import load_machine as load
from xmalign.post.stream_assign import assign_stream

OPTIONS = StreamOptions(clock_offset_s=731.25, clock_rate_ppm=-120.0, servo_lag_s=0.02)


@pytest.fixture(scope="module")
def machine() -> Machine:
    return load(default_machine_path())


@pytest.fixture(scope="module")
def program(machine: Machine) -> InstrumentProgram:
    return InstrumentProgram(paths_mm=fly_paths(machine))


@pytest.fixture(scope="module")
def recorded(machine: Machine, program: InstrumentProgram) -> StreamRun:
    truth = VirtualMachine(machine, ErrorAmplitudes(), seed=4)
    tracker = VirtualTracker(tracker_place(machine), np.array([0.3, -0.8, 75.0]), seed=4)
    return record_stream(machine, truth, tracker, program, OPTIONS)


def _files(folder: Path, machine: Machine, program: InstrumentProgram, run: StreamRun) -> None:
    write_tracker_stream(folder / "stream.csv", [run])
    atomic_write_text(folder / "points.csv", point_list_csv(program, machine.smr_offset))


def _import(folder: Path):
    return run_cli(
        "import",
        "--tracker-stream",
        "stream.csv",
        "--points",
        "points.csv",
        "--out",
        "tracker.csv",
        cwd=folder,
    )


def test_the_import_keeps_each_path_at_its_cruise_speed_and_nothing_else(
    tmp_path, machine, program, recorded
):
    _files(tmp_path, machine, program, recorded)
    result = _import(tmp_path)
    assert result.returncode == 0, result.stderr
    rows = read_tracker_points(tmp_path / "tracker.csv").points
    assert all(p.index is None and p.to_mm is not None for p in rows)
    # where the simulated CNC really was at each kept sample (its own clock, lag)
    timeline = program_timeline(machine, program, None)
    time_s = np.array([p.time_s for p in rows])
    cnc_s = (time_s - OPTIONS.clock_offset_s) / (1 + OPTIONS.clock_rate_ppm * 1e-6)
    cnc_s -= OPTIONS.servo_lag_s
    move = np.searchsorted(timeline.t0_s, cnc_s, side="right") - 1
    since = cnc_s - timeline.t0_s[move]
    ramp = timeline.peak_mm_s[move] / timeline.accel_mm_s2
    assert np.all(since >= ramp) and np.all(since <= timeline.duration_s[move] - ramp)
    starts = np.array([p.machine_mm for p in rows])
    ends = np.array([p.to_mm for p in rows])
    np.testing.assert_allclose(timeline.start_mm[move], starts, atol=2e-3)
    np.testing.assert_allclose(timeline.end_mm[move], ends, atol=2e-3)
    # every path is there, with most of its cruise
    assert len({(*s, *e) for s, e in zip(starts, ends, strict=True)}) == len(program.paths_mm)
    cruise_s = sum(
        timeline.duration_s[k] - 2 * timeline.peak_mm_s[k] / timeline.accel_mm_s2
        for k in set(move.tolist())
    )
    assert len(rows) > 0.85 * cruise_s * OPTIONS.rate_hz
    # history: both inputs' SHA-256
    text = (tmp_path / "tracker.csv").read_text()
    for role, name in (("stream", "stream.csv"), ("points", "points.csv")):
        assert f"# input {role}: {file_sha256(tmp_path / name)}  {name}" in text
    assert "71 paths" in result.stderr


def test_a_stream_read_back_is_the_stream_written(tmp_path, recorded):
    write_tracker_stream(tmp_path / "s.csv", [recorded])
    (run,) = list(read_tracker_stream(tmp_path / "s.csv").runs())
    assert (run.station, run.run) == (recorded.station, recorded.run)
    np.testing.assert_allclose(run.time_s, recorded.time_s, atol=1e-5)
    np.testing.assert_allclose(run.tracker_mm, recorded.tracker_mm, atol=1e-5)


def _assign(run: StreamRun, program: InstrumentProgram, machine: Machine):
    starts = np.array([s for s, _ in program.paths_mm]) + machine.smr_offset
    ends = np.array([e for _, e in program.paths_mm]) + machine.smr_offset
    return assign_stream(
        run.time_s, run.tracker_mm, starts, ends, np.arange(len(run.time_s)) + 3, "s.csv"
    )


def test_a_tracker_that_stood_still_is_told(machine, program, recorded):
    rng = np.random.default_rng(0)
    still = StreamRun(
        "T1",
        0,
        recorded.time_s[:5000],
        recorded.tracker_mm[0] + rng.normal(0, 0.01, (5000, 3)),
        recorded.u_radial_um[:5000],
        recorded.u_transverse_um[:5000],
        recorded.line[:5000],
    )
    with pytest.raises(InputError, match="stood still"):
        _assign(still, program, machine)


def test_a_stream_of_another_program_is_told(machine, recorded):
    other = InstrumentProgram(paths_mm=fly_paths(machine, seed=7))
    with pytest.raises(InputError, match="another program"):
        _assign(recorded, other, machine)


def test_a_gap_in_the_stream_names_its_line(tmp_path, machine, program, recorded):
    keep = np.ones(len(recorded.time_s), dtype=bool)
    keep[40_000:40_030] = False  # 0.3 s without a sample, the SMR on a path
    gapped = StreamRun(
        "T1",
        0,
        recorded.time_s[keep],
        recorded.tracker_mm[keep],
        recorded.u_radial_um[keep],
        recorded.u_transverse_um[keep],
        recorded.line[keep],
    )
    _files(tmp_path, machine, program, gapped)
    result = _import(tmp_path)
    # the history lines and the header come first
    lines = (tmp_path / "stream.csv").read_text().splitlines()
    first_row = 1 + next(n for n, line in enumerate(lines, 1) if not line.startswith("#"))
    assert_one_line_error(result, "stream.csv", f"line {first_row + 40_000}", "gap")
    assert not (tmp_path / "tracker.csv").exists()


def test_time_that_goes_back_names_its_line(tmp_path):
    text = "# xmalign tracker-stream/1\nstation,run,time_s,tx_mm,ty_mm,tz_mm\n"
    text += "".join(f"T1,0,{t},1.0,2.0,3.0\n" for t in (0.0, 0.01, 0.02, 0.015, 0.03))
    (tmp_path / "stream.csv").write_text(text)
    atomic_write_text(
        tmp_path / "points.csv", "name,x_mm,y_mm,z_mm\npath 0 start,0,0,0\npath 0 end,1,0,0\n"
    )
    assert_one_line_error(_import(tmp_path), "stream.csv", "line 6", "time_s")


def test_a_point_list_without_paths_is_refused(tmp_path, machine, program, recorded):
    _files(tmp_path, machine, program, recorded)
    atomic_write_text(tmp_path / "points.csv", "name,x_mm,y_mm,z_mm\n0,1,2,3\n")
    assert_one_line_error(_import(tmp_path), "points.csv", "no paths")


def test_a_bad_stream_row_names_its_line(tmp_path):
    text = "# xmalign tracker-stream/1\nstation,run,time_s,tx_mm,ty_mm,tz_mm\n"
    text += "T1,0,0.0,1.0,2.0,3.0\nT1,0,0.01,1.0,x,3.0\n"
    (tmp_path / "stream.csv").write_text(text)
    atomic_write_text(
        tmp_path / "points.csv", "name,x_mm,y_mm,z_mm\npath 0 start,0,0,0\npath 0 end,1,0,0\n"
    )
    assert_one_line_error(_import(tmp_path), "stream.csv", "line 4", "ty_mm")


def test_the_dry_run_on_the_fly_goes_through_the_stream_and_the_import(tmp_path):
    out = tmp_path / "dry"
    result = run_in_process(
        "dry-run", "--instrument", "tracker", "--on-the-fly", "--out", str(out), "--seed", "2"
    )
    assert result.returncode == 0, result.stderr
    assert (out / "tracker-stream.csv").exists() and (out / "points.csv").exists()
    rows = read_tracker_points(out / "tracker.csv")
    assert all(p.index is None for p in rows.points)
    stream_sha256 = file_sha256(out / "tracker-stream.csv")
    assert any(c.startswith(f"# input stream: {stream_sha256}") for c in rows.comments)
    assert "noise correlated over" in result.stderr
    after = float(result.stdout.split(" after ")[1].split(" um")[0])
    assert after < 2.5  # standstill: about 4 um (bench_tracker_stream.py)


def test_on_the_fly_is_for_the_tracker_dry_run(tmp_path):
    result = run_in_process(
        "dry-run", "--instrument", "tracer", "--on-the-fly", "--out", str(tmp_path / "d")
    )
    assert_one_line_error(result, "--on-the-fly", "tracker")


def test_each_run_of_a_stream_is_assigned_on_its_own_and_keeps_its_uncertainty(
    tmp_path, machine, program, recorded
):
    second = StreamRun(
        "T1",
        1,
        recorded.time_s + 9000.0,  # the tracker's clock ran on between the runs
        recorded.tracker_mm,
        np.full(len(recorded.time_s), 11.0),
        np.full(len(recorded.time_s), 12.5),
        recorded.line,
    )
    write_tracker_stream(tmp_path / "stream.csv", [recorded, second])
    atomic_write_text(tmp_path / "points.csv", point_list_csv(program, machine.smr_offset))
    result = _import(tmp_path)
    assert result.returncode == 0, result.stderr
    rows = read_tracker_points(tmp_path / "tracker.csv").points
    runs = np.array([p.run for p in rows])
    assert set(runs.tolist()) == {0, 1} and np.sum(runs == 0) == np.sum(runs == 1)
    assert {(p.u_radial_um, p.u_transverse_um) for p in rows if p.run == 1} == {(11.0, 12.5)}
    assert all(p.u_radial_um is None for p in rows if p.run == 0)
    assert "station T1 run 1" in result.stderr
