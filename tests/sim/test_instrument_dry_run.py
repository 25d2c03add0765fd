"""``xmalign dry-run --instrument tracer --simultaneous``: tracers at once, through the CLI."""

from __future__ import annotations

from pathlib import Path

from cli_helpers import assert_one_line_error, run_in_process

from xmalign.formats.instruments import read_tracer_lengths


def _after_um(stdout: str) -> float:
    return float(stdout.split(" after ")[1].split(" um")[0])


def test_tracers_at_once_take_a_quarter_of_the_time_and_measure_as_well(tmp_path: Path) -> None:
    """The same machine (seed 2) one place at a time and all at once: a quarter of the
    machine time, the same volumetric error within 0.1 um (the accuracy of the tracer
    fit itself is tests/xmalign/post's)."""
    out = tmp_path / "dry"
    result = run_in_process(
        "dry-run", "--instrument", "tracer", "--simultaneous", "--out", str(out), "--seed", "2"
    )
    assert result.returncode == 0, result.stderr
    time = result.stdout.split("machine time: tracer ")[1]
    together = float(time.split(" min")[0])
    apart = float(time.split("one place at a time: ")[1].split(" min")[0])
    assert abs(together / apart - 0.25) < 0.01
    one_at_a_time = run_in_process(
        "dry-run", "--instrument", "tracer", "--out", str(tmp_path / "apart"), "--seed", "2"
    )
    assert one_at_a_time.returncode == 0, one_at_a_time.stderr
    assert _after_um(result.stdout) < _after_um(one_at_a_time.stdout) + 0.1
    assert (
        "tracer scale 0.5 ppm per run" in result.stdout and "SMR positions A, B, C" in result.stdout
    )
    lengths = read_tracer_lengths(out / "tracer.csv").lengths
    stations = {r.station for r in lengths}
    assert stations == {"P1", "P2", "P3", "P4"}
    readings = [{(r.run, r.index, r.smr) for r in lengths if r.station == s} for s in stations]
    assert all(r == readings[0] for r in readings)  # every tracer in the same runs
    assert {r.smr for r in lengths} == {"A", "B", "C"}
    assert all(r.material_c is not None and 20.6 <= r.material_c <= 21.4 for r in lengths)


def test_simultaneous_is_for_tracers(tmp_path: Path) -> None:
    for instrument in ("tracker", "xm60"):
        result = run_in_process(
            "dry-run", "--instrument", instrument, "--simultaneous", "--out", str(tmp_path / "d")
        )
        assert_one_line_error(result, "--simultaneous is for --instrument tracer")
    assert_one_line_error(
        run_in_process("program", "--instrument", "tracker", "--simultaneous"),
        "--simultaneous is for --instrument tracer",
    )
    assert_one_line_error(run_in_process("program", "--simultaneous"), "--simultaneous needs")
