"""G-code: LinuxCNC's own interpreter, syntax rules from the controller manuals,
and a round trip through the simulated CNC for every dialect."""

from __future__ import annotations

import re
import shutil
import subprocess

import numpy as np
import pytest
from required_tools import LINUXCNC_REQUIRED

from sim.clock import SimClock
from sim.cnc import SimulatedCnc
from trajectories.gcode import DIALECTS, make_dialect
from trajectories.gcode.program import write_program
from trajectories.planner import plan_measurement
from xmalign.errors import InputError, OutOfRangeError
from xmalign.machine import WorkOffset

GCODE_RESOLUTION_MM = 0.5e-3 + 1e-9
#: Skip without rs274, unless .ci/run requires LinuxCNC (then the test fails running it).
RS274_MISSING = shutil.which("rs274") is None and not LINUXCNC_REQUIRED


@pytest.fixture
def plan(machine, pose):
    return plan_measurement(machine, pose).plan


def expected_dwell_points(plan) -> np.ndarray:
    points = []
    for line in plan.lines:
        targets = line.target_points_mm()
        for _ in range(line.runs):
            points.extend(targets)
            if line.bidirectional:
                points.extend(targets[::-1])
        points.append(targets[0])  # the drift check
    return np.array(points)


@pytest.mark.skipif(RS274_MISSING, reason="LinuxCNC's rs274 is not on PATH")
def test_linuxcnc_program_passes_rs274_and_dwells_at_every_target(tmp_path, machine, plan):
    path = tmp_path / "run.ngc"
    path.write_text(write_program(plan, machine, DIALECTS["linuxcnc"]()))
    result = subprocess.run(
        ["rs274", "-g", str(path)],
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr
    canon = result.stdout
    assert "PROGRAM_END()" in canon
    feeds = [
        np.array([float(v) for v in m.groups()])
        for m in re.finditer(r"STRAIGHT_FEED\(([-\d.]+), ([-\d.]+), ([-\d.]+),", canon)
    ]
    dwell_blocks = re.findall(rf"DWELL\({plan.lines[0].dwell_s:.4f}\)", canon)
    expected = expected_dwell_points(plan)
    assert len(dwell_blocks) == len(expected)
    lines = canon.splitlines()
    dwell_points = []
    last = None
    for text in lines:
        move = re.search(r"STRAIGHT_FEED\(([-\d.]+), ([-\d.]+), ([-\d.]+),", text)
        if move:
            last = np.array([float(v) for v in move.groups()])
        if "DWELL(" in text:
            dwell_points.append(last)
    np.testing.assert_allclose(np.array(dwell_points), expected, rtol=0, atol=GCODE_RESOLUTION_MM)
    assert len(feeds) > len(expected)


@pytest.mark.parametrize("dialect", sorted(DIALECTS))
def test_every_dialect_runs_on_the_simulated_cnc_and_visits_exactly_the_targets(
    dialect, machine, plan
):
    text = write_program(plan, machine, DIALECTS[dialect]())
    clock = SimClock()
    cnc = SimulatedCnc(machine, clock)
    events = list(cnc.run_program(text, dialect))
    dwells = [e for e in events if e.kind == "dwell"]
    # The programs carry coordinates to 1 um (3 decimals), so "exactly" is within 0.5 um.
    np.testing.assert_allclose(
        [e.position_mm for e in dwells],
        expected_dwell_points(plan),
        rtol=0,
        atol=GCODE_RESOLUTION_MM,
    )
    assert all(e.dwell_s == pytest.approx(plan.lines[0].dwell_s) for e in dwells)
    assert re.fullmatch(r"X run 1 \+ target 1/\d+ at 0\.000 mm", dwells[0].text)
    assert [e.kind for e in events].count("stop") == len(plan.lines)
    assert events[-1].kind == "end"
    assert cnc.is_standstill()
    assert cnc.position_mm()[2] == pytest.approx(machine.travel_max_mm[2])
    if dialect in ("sinumerik", "linuxcnc"):  # the others have no message block
        assert any(e.kind == "message" and "LINE X" in e.text for e in events)


def _blocks(text: str) -> list[str]:
    return text.splitlines()


COORDS = r"( [XYZ]-?\d+\.\d{3})+"


def test_iso_fanuc_syntax_sets_its_own_work_offset_and_retracts_in_g53(machine, plan):
    blocks = _blocks(write_program(plan, machine, DIALECTS["iso"]()))
    assert blocks[0] == "%" and blocks[-1] == "%" and blocks[-2] == "M30"
    assert re.fullmatch(r"O\d{4} \([A-Z0-9 ]*\)", blocks[1])
    # radius, length, cycles off; local system off; G59 written to machine zero and selected
    assert blocks[2:6] == [
        "G21 G90 G94 G17 G40 G49 G80",
        "G52 X0. Y0. Z0.",
        "G10 L2 P6 X0.000 Y0.000 Z0.000",
        "G59",
    ]
    for block in blocks[6:-1]:
        assert re.fullmatch(
            rf"\([^()]*\)|M00|M30|G04 P\d+|(G53 )?G00{COORDS}|G01{COORDS} F\d+\.\d",
            block,
        ), block
    # G53 is rapid only on Fanuc: every retract uses it, no feed move does
    assert all(b.startswith("G53 G00 Z") for b in blocks if b.startswith("G53"))
    assert f"G04 P{round(plan.lines[0].dwell_s * 1000)}" in blocks


def test_sinumerik_syntax_moves_with_supa(machine, plan):
    blocks = _blocks(write_program(plan, machine, DIALECTS["sinumerik"]()))
    assert blocks[-1] == "M30" and blocks[1:3] == ["G71 G90 G94 G17 G40", "D0"]
    for block in blocks:
        assert re.fullmatch(
            r'; [^\n]*|G71 G90 G94 G17 G40|D0|M0|M30|MSG\("[^"]*"\)|MSG\(\)|G4 F\d+\.\d+'
            rf"|SUPA G0{COORDS}|SUPA G1{COORDS} F\d+\.\d",
            block,
        ), block
    assert f"G4 F{plan.lines[0].dwell_s:.3f}" in blocks


def test_heidenhain_conversational_syntax_cancels_the_tool_and_moves_with_m91(machine, plan):
    blocks = _blocks(write_program(plan, machine, DIALECTS["heidenhain"]("RUN")))
    numbers = [int(b.split(" ", 1)[0]) for b in blocks]
    assert numbers == list(range(len(blocks)))
    contents = [b.split(" ", 1)[1] for b in blocks]
    assert contents[0] == "BEGIN PGM RUN MM" and contents[-1] == "END PGM RUN MM"
    assert contents[1] == "TOOL CALL 0 Z"  # length 0: no tool length compensation
    assert contents[-2].endswith("M91 M30")
    for i, content in enumerate(contents[2:-1], start=2):
        assert re.fullmatch(
            r"; [^\n]*|STOP|CYCL DEF 9\.0 DWELL TIME|CYCL DEF 9\.1 DWELL \d+\.\d+"
            r"|L( [XYZ][+-]\d+\.\d{3})+ R0 (FMAX|F\d+) M91( M30)?",
            content,
        ), content
        if content.startswith("CYCL DEF 9.1"):
            assert contents[i - 1] == "CYCL DEF 9.0 DWELL TIME"


def test_linuxcnc_moves_with_g53_after_cancelling_offsets(machine, plan):
    blocks = _blocks(write_program(plan, machine, DIALECTS["linuxcnc"]()))
    assert blocks[2] == "G21 G90 G94 G17 G40 G49 G80"
    moves = [b for b in blocks if re.match(r"(G53 )?G[01] ", b)]
    assert moves and all(b.startswith("G53 ") for b in moves)


def _with_work_offset(machine, origin):
    return machine.model_copy(
        update={
            "cnc": machine.cnc.model_copy(
                update={"work_offset": WorkOffset(code="G55", origin_mm=origin)}
            )
        }
    )


@pytest.mark.parametrize("dialect", ["iso", "linuxcnc", "sinumerik"])
def test_a_work_offset_from_the_machine_file_is_set_and_converted(dialect, machine, plan):
    """Program coordinates = machine - origin; the simulated CNC still reaches the targets."""
    origin = [100.0, 50.0, -20.0]
    shifted = _with_work_offset(machine, origin)
    text = write_program(plan, shifted, make_dialect(dialect, shifted))
    assert "G55" in text.splitlines()
    first = plan.lines[0].target_points_mm()[0]
    x_word = f"X{first[0] - origin[0]:.3f} Y{first[1] - origin[1]:.3f}"
    assert any(x_word in block for block in text.splitlines())
    cnc = SimulatedCnc(shifted, SimClock())
    dwells = [e for e in cnc.run_program(text, dialect) if e.kind == "dwell"]
    np.testing.assert_allclose(
        [e.position_mm for e in dwells],
        expected_dwell_points(plan),
        rtol=0,
        atol=GCODE_RESOLUTION_MM,
    )


def test_heidenhain_refuses_a_work_offset(machine):
    with pytest.raises(InputError, match="cnc.work_offset"):
        make_dialect("heidenhain", _with_work_offset(machine, [0.0, 0.0, 0.0]))


@pytest.mark.skipif(RS274_MISSING, reason="LinuxCNC's rs274 is not on PATH")
def test_linuxcnc_work_offset_is_what_rs274_sets(tmp_path, machine, plan):
    origin = [100.0, 50.0, -20.0]
    shifted = _with_work_offset(machine, origin)
    path = tmp_path / "run.ngc"
    path.write_text(write_program(plan, shifted, make_dialect("linuxcnc", shifted)))
    canon = subprocess.run(
        ["rs274", "-g", str(path)],
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=60,
    ).stdout
    offset = re.search(r"SET_G5X_OFFSET\(2, ([-\d.]+), ([-\d.]+), ([-\d.]+)", canon)
    assert offset is not None and [float(v) for v in offset.groups()] == origin
    assert "PROGRAM_END()" in canon


def test_cli_program_names_the_heidenhain_program_after_its_file(tmp_path):
    from tests.cli_helpers import run_cli
    from tests.trajectories.conftest import make_pose
    from xmalign.formats.pose import write_pose

    write_pose(tmp_path / "pose.json", make_pose())
    out = tmp_path / "CALIB1.h"
    result = run_cli(
        "program",
        "--pose",
        str(tmp_path / "pose.json"),
        "--dialect",
        "heidenhain",
        "--out",
        str(out),
    )
    assert result.returncode == 0, result.stderr
    lines = out.read_text().splitlines()
    assert lines[0] == "0 BEGIN PGM CALIB1 MM" and lines[-1].endswith("END PGM CALIB1 MM")


def test_target_outside_travel_is_refused(machine, plan):
    plan.lines[0].targets_mm = plan.lines[0].targets_mm + 100.0
    with pytest.raises(OutOfRangeError, match=r"line X: target \d+ .* outside the travel"):
        write_program(plan, machine, DIALECTS["iso"]())


@pytest.mark.parametrize("dialect", sorted(DIALECTS))
def test_every_program_carries_its_history_and_still_runs(dialect, tmp_path, machine, plan):
    """Format, software, time and the plan file's SHA-256 as the dialect's own comments
    (the file named without its folder, a long name cut short); the program still runs on
    the simulated CNC and, for LinuxCNC, in LinuxCNC's own rs274."""
    import hashlib

    from xmalign.formats.plan import read_plan, write_plan

    path = tmp_path / ("p" * 120 + ".json")
    write_plan(path, plan)
    text = write_program(read_plan(path), machine, DIALECTS[dialect]("RUN"))
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    mark = {"iso": "(", "linuxcnc": "(", "sinumerik": "; ", "heidenhain": "; "}[dialect]
    assert f"{mark}format: xmalign.program/1" in text
    assert f"{mark}software: xmalign " in text and f"{mark}created_utc: 20" in text
    assert f"{mark}input plan: {digest}  {'p' * 80}..." in text
    assert f"{mark}dialect: {dialect}" in text
    assert all(len(line) < 200 for line in text.splitlines())
    events = list(SimulatedCnc(machine, SimClock()).run_program(text, dialect))
    assert events[-1].kind == "end"
    if dialect == "linuxcnc" and not RS274_MISSING:
        program = tmp_path / "run.ngc"
        program.write_text(text)
        result = subprocess.run(
            ["rs274", "-g", str(program)],
            stdin=subprocess.DEVNULL,
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert result.returncode == 0, result.stdout[-2000:] + result.stderr
        assert f'COMMENT("input plan: {digest}' in result.stdout
