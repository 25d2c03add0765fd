"""Shared fixtures."""

from __future__ import annotations

import os

# One BLAS thread per process, set before numpy loads (xmalign imports it below) and
# inherited by the CLI subprocesses: the suite runs a process per core, and OpenBLAS's
# second thread then spins on a busy core (a dry run: 6.9 s CPU with it, 3.3 s without).
for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

import shutil  # noqa: E402
from collections.abc import Generator  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

from xmalign.machine import Machine, load_machine  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def reference_machine_path() -> Path:
    return ROOT / "examples" / "fyxz.yaml"


@pytest.fixture(scope="session")
def reference_machine(reference_machine_path: Path) -> Machine:
    return load_machine(reference_machine_path)


LINUXCNC_TESTS = "tests/linuxcnc/"


@pytest.hookimpl(optionalhook=True, wrapper=True)
def pytest_xdist_auto_num_workers(config: pytest.Config) -> Generator[None, int, int]:
    """``-n auto``: one worker per core, and one more for the LinuxCNC group when LinuxCNC is
    installed. That worker mostly waits (a real-time LinuxCNC takes well under a tenth of
    a core); without it one core idles for the LinuxCNC group's minutes."""
    workers = yield
    if os.environ.get("PYTEST_XDIST_AUTO_NUM_WORKERS") or shutil.which("linuxcnc") is None:
        return workers
    return workers + 1


def xdist_group(nodeid: str) -> str:
    """The work unit of a test: every LinuxCNC test together (only one LinuxCNC runs per
    host, tests/linuxcnc/harness.py), otherwise its module (module fixtures run once)."""
    return "linuxcnc" if nodeid.startswith(LINUXCNC_TESTS) else nodeid.split("::")[0]


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: object) -> object:
    """Hand pytest-xdist's workers whole groups (:func:`xdist_group`), the LinuxCNC group first.

    Its own ``--dist loadgroup`` has no effect with pytest 9 (xdist 3.8 renames
    ``item._nodeid``, which pytest 9 no longer reads): every test went to any worker,
    module fixtures ran on both and the LinuxCNC tests waited for each other's lock.
    Largest groups go first (xdist's ``--loadscope-reorder``); the LinuxCNC group,
    the longest, before all, so the other worker shares out the rest meanwhile.
    """
    from xdist.scheduler import LoadScopeScheduling

    class GroupScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return xdist_group(nodeid)

        def _assign_work_unit(self, node: object) -> None:
            if "linuxcnc" in self.workqueue:
                self.workqueue.move_to_end("linuxcnc", last=False)
            super()._assign_work_unit(node)

    return GroupScheduling(config, log)
