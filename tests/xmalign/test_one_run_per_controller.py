"""One run per controller (issue 32, item 5): the lock beside xmalign's program, the run's
id in the program, and a second ``xmalign run`` on ``sim serve --linuxcncrsh`` while a
first one runs its program there (refused in one line naming the first, nothing touched)."""

from __future__ import annotations

import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from cli_helpers import Process

from tests.xmalign.test_live_controlled_e2e import RUN, served  # noqa: F401 - fixture
from tests.xmalign.test_live_e2e import short_plan  # noqa: F401 - fixture
from xmalign.calibration.controller_lock import ControllerLock, lock_path, new_run_id
from xmalign.errors import InputError, OutputError


def test_a_second_lock_is_refused_naming_the_first_run_until_it_is_released(tmp_path):
    program = tmp_path / "run.ngc"
    first = ControllerLock(program, "RUN-1", tmp_path / "first.csv")
    with pytest.raises(InputError) as caught:
        ControllerLock(program, "RUN-2", tmp_path / "second.csv")
    line = str(caught.value)
    assert line.startswith(f"{program}: another xmalign run is in progress on this controller (run")
    assert f"run RUN-1, measuring into {tmp_path / 'first.csv'}, started " in line
    assert line.endswith("wait until it ends, or stop it, then run again") and "\n" not in line
    first.release()
    with ControllerLock(program, "RUN-2", tmp_path / "second.csv"):
        assert "RUN-2" in lock_path(program).read_text()


def test_the_lock_ends_with_a_killed_run(tmp_path):
    program = tmp_path / "run.ngc"
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from pathlib import Path;"
         " from xmalign.calibration.controller_lock import ControllerLock;"
         " lock = ControllerLock(Path(sys.argv[1]), 'KILLED', Path('m.csv'));"
         " print('held', flush=True); time.sleep(60)", str(program)],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        with pytest.raises(InputError, match="run KILLED"):
            ControllerLock(program, "NEXT", tmp_path / "m.csv")
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    with ControllerLock(program, "NEXT", tmp_path / "m.csv"):
        pass


def test_a_folder_where_no_lock_can_be_made_is_one_line(tmp_path):
    with pytest.raises(OutputError, match="cannot create the run lock beside the program"):
        ControllerLock(tmp_path / "missing" / "run.ngc", new_run_id(), tmp_path / "m.csv")


def test_a_run_on_a_controller_with_a_run_in_progress_is_refused_and_touches_nothing(
    served: Process,  # noqa: F811 - fixture
    tmp_path: Path,
) -> None:
    """Another run (another computer on the share) holds the controller: ``xmalign run``
    is refused in one line naming it, before it writes the program or commands the
    controller; once that run has ended, it runs."""
    other = "20261127T080000Z-bench2-4242"
    lock = ControllerLock(tmp_path / "run.ngc", other, Path("/shop/first.csv"))
    try:
        refused = Process([*RUN, "--out", "m.csv"], tmp_path)
        assert refused.finish(timeout_s=60) == 2, refused.said()
    finally:
        lock.release()
    (line,) = [text for text in refused.stderr.splitlines() if text.strip()]
    assert line.startswith(
        "xmalign: error: run.ngc: another xmalign run is in progress on this"
        f" controller (run {other}, measuring into /shop/first.csv, started "
    )
    assert not (tmp_path / "run.ngc").exists()
    assert "> 'set" not in served.said()  # nothing was sent to the controller
    run = Process([*RUN, "--out", "m2.csv"], tmp_path)
    assert run.finish(timeout_s=120) == 0, run.said() + served.said()
    program = (tmp_path / "run.ngc").read_text()
    (run_id,) = re.findall(r"\(xmalign run (\S+)\)", program)
    assert run_id.endswith(f"-{run.popen.pid}")
