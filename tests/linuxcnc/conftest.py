"""Fixtures for tests that run a real headless LinuxCNC (see harness.py)."""

from __future__ import annotations

import functools
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from harness import linuxcnc_available
from required_tools import skip_unless_required


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers",
        "linuxcnc: starts a real headless LinuxCNC (skipped when it is not installed,"
        " failed under XMALIGN_REQUIRE_LINUXCNC=1)",
    )


@functools.cache
def _linuxcnc_installed() -> bool:
    return linuxcnc_available()


@pytest.fixture(autouse=True)
def _linuxcnc_present(request: pytest.FixtureRequest) -> None:
    """A ``linuxcnc`` test without LinuxCNC: skipped, or failed under
    XMALIGN_REQUIRE_LINUXCNC=1 (.ci/run; tests/required_tools.py)."""
    if "linuxcnc" in request.keywords and not _linuxcnc_installed():
        skip_unless_required("LinuxCNC (Debian linuxcnc-uspace) is not installed")


@pytest.fixture
def linuxcnc_dir() -> Iterator[Path]:
    """A folder the LinuxCNC user can write (pytest's tmp_path is private to root)."""
    folder = Path(tempfile.mkdtemp(prefix="xmalign-linuxcnc-"))
    folder.chmod(0o777)
    yield folder
    shutil.rmtree(folder, ignore_errors=True)
