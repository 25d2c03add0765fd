"""The Python API (issue 23, item 3): docs/api.md runs as written, the example plots."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from xmalign import api

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "api.md"


def _blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", PAGE.read_text(), re.S)


@pytest.fixture(scope="module")
def page_session(tmp_path_factory) -> dict:
    """Every python block of docs/api.md run in order in one namespace, from a folder
    laid out as the repository's root (its examples/)."""
    folder = tmp_path_factory.mktemp("api-page")
    (folder / "examples").symlink_to(ROOT / "examples")
    namespace: dict = {}
    cwd = Path.cwd()
    os.chdir(folder)
    try:
        for block in _blocks():
            exec(compile(block, str(PAGE), "exec"), namespace)
    finally:
        os.chdir(cwd)
    namespace["folder"] = folder
    return namespace


def test_the_page_runs_every_step_and_reads_the_results(page_session):
    work = page_session["folder"] / page_session["work"]
    for name in ("session.json", "pose.json", "plan.json", "measurements.csv", "errors.csv"):
        assert (work / name).is_file()
    assert page_session["identified"].converged
    calibration = page_session["calibration"]
    assert calibration.errors.machine.chain == "FYXZ"
    assert calibration.plan.source.sha256 == api.file_sha256(work / "plan.json")


def test_the_page_uses_only_the_public_surface():
    used = set(re.findall(r"\bapi\.(\w+)", PAGE.read_text()))
    assert used and used <= set(api.__all__), used - set(api.__all__)
    assert all(hasattr(api, name) for name in api.__all__)
    assert api.__all__ == sorted(api.__all__)


def test_the_frames_carry_units_and_the_values_of_the_file(page_session):
    tables = page_session["calibration"].errors
    frames = api.error_table_frames(tables)
    assert sorted(frames) == ["X", "Y", "Z"]
    for axis, frame in frames.items():
        assert frame.index.name == "position_mm"
        pattern = r"E[XYZABC][XYZ][+-]?((_u95)?_(um|urad)|_measured)"
        assert all(re.fullmatch(pattern, column) for column in frame)
        for name, table in tables.tables.items():
            if name.rstrip("+-").endswith(axis):
                unit = "urad" if name[1] in "ABC" else "um"
                column = frame[f"{name}_{unit}"].dropna()
                scale = 1e6 if unit == "urad" else 1e3
                np.testing.assert_allclose(column.to_numpy(), table.values * scale)
    points = api.measurements_frame(page_session["calibration"].measurements)
    assert len(points) == len(page_session["calibration"].measurements.rows)
    assert points["time_s"].notna().all() and points["time_s"].is_monotonic_increasing
    figures = api.iso230_2_frame(page_session["posted"].post)
    assert list(figures.index) == ["X", "Y", "Z"] and (figures["A_um"] > 0).all()
    square = api.squareness_frame(tables)
    assert list(square.columns) == ["value_urad", "u95_urad"]


def test_without_pandas_the_frames_say_how_to_get_it(monkeypatch):
    monkeypatch.setitem(sys.modules, "pandas", None)
    with pytest.raises(ImportError, match=r"pip install 'xmalign\[pandas\]'"):
        api.squareness_frame(api.read_error_tables(ROOT / "examples" / "errors.csv"))


def test_the_notebook_example_plots_the_tables(tmp_path):
    figure = tmp_path / "tables.png"
    done = subprocess.run(
        [
            sys.executable,
            str(ROOT / "examples" / "plot_error_tables.py"),
            str(ROOT / "examples" / "errors.csv"),
            str(figure),
        ],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "MPLBACKEND": "Agg", "PYTHONPATH": str(ROOT)},
        cwd=tmp_path,
    )
    assert done.returncode == 0, done.stderr
    assert figure.read_bytes().startswith(b"\x89PNG")
    assert "# %%" in (ROOT / "examples" / "plot_error_tables.py").read_text()
