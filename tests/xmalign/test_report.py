"""The calibration report as a calibration record (HTML and A4 PDF)."""

from __future__ import annotations

import shutil
import subprocess
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest

from sim.machine import VirtualMachine
from sim.synthetic import measure, six_line_plan
from xmalign.environment import DriftCheck, Range
from xmalign.post.evaluate import PostResult, post_process
from xmalign.report import (
    RecordInfo,
    Table,
    _text_lines,
    budget_table,
    render_report,
    report_tables,
    write_report,
)
from xmalign.rigid_body import Chain


def _result(machine, runs: int, seed: int) -> PostResult:
    plan = six_line_plan(machine, 8, runs=runs, bidirectional=True)
    rows = measure(
        plan,
        Chain.parse(machine.chain),
        VirtualMachine(machine, seed=seed),
        np.random.default_rng(seed),
    )
    return post_process(machine, plan, rows, "synthetic")


@pytest.fixture(scope="module")
def found(reference_machine) -> PostResult:
    return _result(reference_machine, runs=2, seed=4)


@pytest.fixture(scope="module")
def info(reference_machine) -> RecordInfo:
    ranges = {
        "air_temp_c": Range(22.0, 23.0, 24.0),
        "air_pressure_hpa": Range(974.0, 975.0, 976.0),
        "air_humidity_percent": Range(45.0, 50.0, 55.0),
        "material_temp_c": Range(22.0, 22.5, 23.0),
    }
    return RecordInfo(
        operator="A. Engineer",
        created=datetime(2026, 3, 1, 9, 30, tzinfo=UTC),
        instruments={"interferometer": "XM60-1234", "weather station": "XC80-0042"},
        environment={"X": ranges, "Y": ranges},
        compensation="air compensated (modified Edlén), dead path included",
        drift=[DriftCheck("X", 0.4, 2.0), DriftCheck("Y", 3.1, 2.0)],
        vdi3441=True,
    )


@pytest.fixture(scope="module")
def record_html(reference_machine, found, info) -> str:
    left = _result(reference_machine, runs=5, seed=5)
    record = RecordInfo(**{**info.__dict__, "verification": left})
    return render_report(reference_machine, found, "sinumerik", record)


def test_html_is_a_calibration_record(record_html: str) -> None:
    text = record_html
    for fragment in (
        "2026-03-01 09:30:00",
        "xmalign 0.1.0",
        "Example FYXZ gantry mill",
        "EX-0001",
        "A. Engineer",
        "XM60-1234",
        "XC80-0042",
        "22.00/23.00/24.00",
        "EXCEEDED",
        "2 run(s), ISO 230-2 asks for 5",
        "VDI/DGQ 3441",
        "Uncertainty budget",
        "@page{size:A4",
        "img{max-width:100%",
    ):
        assert fragment in text, fragment


def test_without_environment_the_record_says_readings_were_taken_as_compensated(
    reference_machine, found
) -> None:
    tables = {t.title: t for t in report_tables(reference_machine, found, RecordInfo())}
    record = dict(tables["Calibration record"].rows)
    assert "readings taken as already compensated" in record["compensation"]
    assert record["operator"] == "not given"
    assert (
        tables["Environment per line"].note == "No environment was recorded with the measurement."
    )
    assert "VDI/DGQ 3441 figures (um)" not in tables


def test_budget_adds_the_environment_to_the_positioning_errors_only(
    reference_machine, found, info
) -> None:
    rows = {row[0]: row for row in budget_table(reference_machine, found, info).rows}
    fit, air, material, alpha, combined = (float(v) for v in rows["EXX"][2:])
    assert air > 0 and material > 0 and alpha > 0
    assert combined == pytest.approx(np.sqrt(fit**2 + air**2 + material**2 + alpha**2), abs=0.01)
    assert [float(v) for v in rows["EYX"][3:6]] == [0.0, 0.0, 0.0]
    assert "EC0Y" in rows


def test_as_found_as_left(record_html: str) -> None:
    section = record_html.split("As found / as left")[1].split("</table>")[0]
    assert "<td>X</td><td>A</td>" in section and "<td>EC0Y</td>" in section


def test_text_tables_never_exceed_the_page() -> None:
    table = Table("t", ["a", "b"], [["x" * 150, "a long cell " * 20], ["1", "2"]])
    lines = _text_lines(table, 100)
    assert max(len(line) for line in lines) <= 100
    assert "x" * 40 in "".join(lines)


@pytest.mark.skipif(shutil.which("pdftotext") is None, reason="poppler-utils not installed")
def test_pdf_is_a4_and_holds_the_record(reference_machine, found, info, tmp_path: Path) -> None:
    path = tmp_path / "record.pdf"
    write_report(path, reference_machine, found, "sinumerik", info)
    meta = subprocess.run(["pdfinfo", str(path)], capture_output=True, text=True, check=True)
    assert "595.44 x 841.68 pts" in meta.stdout  # A4
    text = subprocess.run(
        ["pdftotext", "-layout", str(path), "-"], capture_output=True, text=True, check=True
    ).stdout
    for fragment in ("EX-0001", "XM60-1234", "EXCEEDED", "asks for 5", "Uncertainty budget"):
        assert fragment in text, fragment


def test_pdf_is_written_atomically_or_not_at_all(reference_machine, found, info, tmp_path: Path):
    """The PDF goes through atomic_write_files like every other file (no own rename)."""
    from xmalign.errors import OutputError

    folder = tmp_path / "record.pdf"
    folder.mkdir()
    with pytest.raises(OutputError, match="record.pdf: cannot write: is a folder"):
        write_report(folder, reference_machine, found, "sinumerik", info)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["record.pdf"]
    kept = tmp_path / "kept.pdf"
    kept.write_bytes(b"the old record")
    write_report(kept, reference_machine, found, "sinumerik", info)
    assert kept.read_bytes().startswith(b"%PDF")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["kept.pdf", "record.pdf"]
