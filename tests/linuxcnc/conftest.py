"""Fixtures for tests that run a real headless LinuxCNC (see harness.py)."""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from harness import linuxcnc_available


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers", "linuxcnc: starts a real headless LinuxCNC (skipped when it is not installed)"
    )


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    if linuxcnc_available():
        return
    skip = pytest.mark.skip(reason="LinuxCNC (Debian linuxcnc-uspace) is not installed")
    for item in items:
        if "linuxcnc" in item.keywords:
            item.add_marker(skip)


@pytest.fixture
def linuxcnc_dir() -> Iterator[Path]:
    """A folder the LinuxCNC user can write (pytest's tmp_path is private to root)."""
    folder = Path(tempfile.mkdtemp(prefix="xmalign-linuxcnc-"))
    folder.chmod(0o777)
    yield folder
    shutil.rmtree(folder, ignore_errors=True)
