"""Shared fixtures."""

from __future__ import annotations

import os

# One BLAS thread per process, set before numpy loads (xmalign imports it below) and
# inherited by the CLI subprocesses: the suite runs a process per core, and OpenBLAS's
# second thread then spins on a busy core (a dry run: 6.9 s CPU with it, 3.3 s without).
for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

import fcntl  # noqa: E402
import pickle  # noqa: E402
import shutil  # noqa: E402
from collections.abc import Callable, Generator  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import pytest  # noqa: E402

from xmalign.machine import Machine, load_machine  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def reference_machine_path() -> Path:
    return ROOT / "examples" / "fyxz.yaml"


@pytest.fixture(scope="session")
def reference_machine(reference_machine_path: Path) -> Machine:
    return load_machine(reference_machine_path)


DryRun = tuple[Any, Path]  # (sim.dry_run.DryRunReport, its own copy of the dry run's folder)


@pytest.fixture(scope="session")
def dry_run_of_seed(
    tmp_path_factory: pytest.TempPathFactory, reference_machine: Machine
) -> Callable[[int, str], DryRun]:
    """``dry_run_of_seed(seed, name)``: the reference machine's dry run with ``seed``
    (default options), as its report and a copy of its folder for the caller to write in.

    The dry run is simulated once per test session, under a lock, in the folder that
    pytest-xdist's workers share; a module asks for its copy in a module fixture.
    """
    from sim.dry_run import DryRunOptions, simulate_calibration

    base = tmp_path_factory.getbasetemp()
    shared = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base

    def dry_run(seed: int, name: str) -> DryRun:
        folder = shared / f"shared-dry-run-seed{seed}"
        with open(shared / f"shared-dry-run-seed{seed}.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            done = folder / "report.pickle"
            if not done.exists():
                shutil.rmtree(folder, ignore_errors=True)
                folder.mkdir()
                options = DryRunOptions(seed=seed)
                report = simulate_calibration(reference_machine, folder, options)
                done.write_bytes(pickle.dumps(report))
        copy = tmp_path_factory.mktemp(name)
        shutil.copytree(folder, copy, dirs_exist_ok=True, ignore=shutil.ignore_patterns("*.pickle"))
        return pickle.loads(done.read_bytes()), copy

    return dry_run


LINUXCNC_TESTS = "tests/linuxcnc/"
#: Groups that mostly wait on real time (a real-time LinuxCNC; served devices running at
#: wall-clock speed), longest first: they start first, on workers of their own.
WAITING_GROUPS = (
    "linuxcnc",
    "tests/xmalign/test_live_e2e.py",
    "tests/xmalign/test_live_identify_e2e.py",
    "tests/xmalign/test_cli_live.py",
)


@pytest.hookimpl(optionalhook=True, wrapper=True)
def pytest_xdist_auto_num_workers(config: pytest.Config) -> Generator[None, int, int]:
    """``-n auto``: one worker per core, and one more for each group that mostly waits
    (:data:`WAITING_GROUPS`; the LinuxCNC group only when LinuxCNC is installed): a
    real-time LinuxCNC or devices served in real time take a fraction of a core, and
    without workers of their own the cores would idle for the minutes they run."""
    workers = yield
    if os.environ.get("PYTEST_XDIST_AUTO_NUM_WORKERS"):
        return workers
    return workers + len(WAITING_GROUPS) - (0 if shutil.which("linuxcnc") else 1)


def xdist_group(nodeid: str) -> str:
    """The work unit of a test: every LinuxCNC test together (only one LinuxCNC runs per
    host, tests/linuxcnc/harness.py), otherwise its module (module fixtures run once)."""
    return "linuxcnc" if nodeid.startswith(LINUXCNC_TESTS) else nodeid.split("::")[0]


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: object) -> object | None:
    """``--dist loadscope`` or ``loadgroup``: hand pytest-xdist's workers whole groups
    (:func:`xdist_group`), the LinuxCNC group first.

    xdist's own ``--dist loadgroup`` has no effect with pytest 9 (xdist 3.8 renames
    ``item._nodeid``, which pytest 9 no longer reads): every test went to any worker,
    module fixtures ran on both and the LinuxCNC tests waited for each other's lock.
    Largest groups go first (xdist's ``--loadscope-reorder``); the :data:`WAITING_GROUPS`
    before all, so the other workers share out the rest meanwhile.
    """
    if config.getoption("dist") not in ("loadscope", "loadgroup"):
        return None  # --dist load, each, worksteal: as pytest-xdist documents them
    from xdist.scheduler import LoadScopeScheduling

    class GroupScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return xdist_group(nodeid)

        def _assign_work_unit(self, node: object) -> None:
            for group in reversed(WAITING_GROUPS):
                if group in self.workqueue:
                    self.workqueue.move_to_end(group, last=False)
            super()._assign_work_unit(node)

    return GroupScheduling(config, log)
