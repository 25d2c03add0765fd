"""One run per controller: a lock beside xmalign's program, and the run's id in the program.

Two ``xmalign run`` on one controller would fight over its program: the second
would take the first's program, open and paused at a stop, for one left by an
earlier run and abort it. A controlled run therefore holds :class:`ControllerLock`
from before it writes the program until it ends: ``fcntl.flock`` on
``<program>.lock`` beside the program file, where every run on that controller
writes its program (on a share, every computer that runs xmalign for that
controller sees it; the lock holds across computers where the share supports
locks, NFS v4 and SMB do). The lock ends with the process that holds it, even a
killed one. The file names the run (its id, the measurement file, the computer,
the process, the start), so the second run is refused with one line naming the
first; the same id is written into the program (:func:`run_id_comment`).
"""

from __future__ import annotations

import errno
import fcntl
import os
import socket
import time
from pathlib import Path

from xmalign.errors import InputError, OutputError

#: The words that begin the run id's comment in xmalign's program.
RUN_ID_WORDS = "xmalign run"


def new_run_id() -> str:
    """An id naming this run: its start (UTC), the computer and the process."""
    started = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    return f"{started}-{socket.gethostname()}-{os.getpid()}"


def run_id_comment(run_id: str) -> str:
    """The comment text that names the run in its program."""
    return f"{RUN_ID_WORDS} {run_id}"


def lock_path(program: Path) -> Path:
    """Where the lock of the controller that runs ``program`` lies: beside it."""
    return program.with_name(program.name + ".lock")


class ControllerLock:
    """Held by the one run on the controller that runs ``program`` (see the module).

    Parameters
    ----------
    program : Path
        The program file xmalign writes for the controller.
    run_id : str
        The run's id (:func:`new_run_id`).
    out : Path
        The run's measurement file (named to a second run).

    Raises
    ------
    InputError
        Another run holds the lock: one line naming it.
    OutputError
        The lock file cannot be created beside the program.
    """

    def __init__(self, program: Path, run_id: str, out: Path) -> None:
        self.path = lock_path(Path(program))
        try:
            self._fd: int | None = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o666)
        except OSError as error:
            raise OutputError(
                f"{self.path}: cannot create the run lock beside the program"
                f" ({error.strerror or error})"
            ) from error
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as error:
            holder = self._holder()
            self.release()
            if error.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):
                raise OutputError(f"{self.path}: cannot lock ({error.strerror})") from error
            raise InputError(
                f"{program}: another xmalign run is in progress on this controller ({holder});"
                " wait until it ends, or stop it, then run again"
            ) from error
        started = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())
        text = (
            f"run {run_id}, measuring into {Path(out).resolve()}, started {started} on"
            f" {socket.gethostname()}, process {os.getpid()}\n"
        )
        os.ftruncate(self._fd, 0)
        os.pwrite(self._fd, text.encode("utf-8"), 0)

    def _holder(self) -> str:
        """What the holder wrote of itself (it may not have written yet)."""
        assert self._fd is not None
        text = os.pread(self._fd, 4096, 0).decode("utf-8", "replace").strip()
        return text or "a run that is starting"

    def release(self) -> None:
        """Let the next run have the controller (closing the file ends the lock)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> ControllerLock:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()
