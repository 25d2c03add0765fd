"""Shared fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest

from xmalign.machine import Machine, load_machine

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def reference_machine_path() -> Path:
    return ROOT / "examples" / "fyxz.yaml"


@pytest.fixture(scope="session")
def reference_machine(reference_machine_path: Path) -> Machine:
    return load_machine(reference_machine_path)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """pytest-xdist groups: a module's tests share a worker (and its module fixtures); one
    worker runs every LinuxCNC test, as only one LinuxCNC runs per host. The LinuxCNC tests,
    the longest group, come first so that the other workers share out the rest meanwhile."""
    for item in items:
        group = "linuxcnc" if "linuxcnc" in item.keywords else item.nodeid.split("::")[0]
        item.add_marker(pytest.mark.xdist_group(group))
    items.sort(key=lambda item: "linuxcnc" not in item.keywords)
