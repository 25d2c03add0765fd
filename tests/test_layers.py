"""The layers are enforced (issue 23, item 4): `lint-imports` checks the contracts of
pyproject.toml ([tool.importlinter], README: Checks); these tests keep the contracts
honest: every core module is under the core's contract, and a core module importing
the simulator breaks it."""

from __future__ import annotations

import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: What is not the core: the command line, the step layer and the API over it.
OUTER = {"cli", "steps", "api", "__main__", "__init__", "data"}


def _config() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]


def test_every_core_module_is_under_the_core_contract():
    core = (
        {
            path.stem
            for path in (ROOT / "xmalign").iterdir()
            if path.suffix == ".py" or path.is_dir()
        }
        - OUTER
        - {"__pycache__"}
    )
    contract = next(c for c in _config()["contracts"] if c["type"] == "forbidden")
    listed = {name.removeprefix("xmalign.") for name in contract["source_modules"]}
    assert listed == core
    assert {"sim", "firmware_iface", "trajectories", "xmalign.cli", "xmalign.steps"} <= set(
        contract["forbidden_modules"]
    )


@pytest.mark.skipif(shutil.which("lint-imports") is None, reason="needs import-linter")
def test_a_core_module_importing_the_simulator_breaks_the_contract(tmp_path):
    copy = tmp_path / "repo"
    ignore = shutil.ignore_patterns("__pycache__", ".git", "tests", "*.egg-info", ".ci")
    for package in ("xmalign", "sim", "firmware_iface", "trajectories"):
        shutil.copytree(ROOT / package, copy / package, ignore=ignore)
    shutil.copy(ROOT / "pyproject.toml", copy / "pyproject.toml")

    def lint() -> subprocess.CompletedProcess:
        return subprocess.run(
            [sys.executable, "-c", "from importlinter.cli import lint_imports_command;"
             " lint_imports_command()"],
            cwd=copy, capture_output=True, text=True, timeout=120,
            env={"PYTHONPATH": str(copy), "PATH": "/usr/bin:/bin"},
        )  # fmt: skip

    kept = lint()
    assert kept.returncode == 0, kept.stdout + kept.stderr
    geometry = copy / "xmalign" / "geometry.py"
    geometry.write_text(geometry.read_text() + "\nimport sim.world  # noqa\n")
    broken = lint()
    assert broken.returncode != 0
    assert "xmalign.geometry -> sim.world" in broken.stdout
