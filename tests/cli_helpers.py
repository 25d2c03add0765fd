"""Running the ``xmalign`` command as a user would, for the CLI tests; a free port.

:class:`Process` runs one in the background (``sim serve``, a live run) and
collects its output lines as they come.

(tests/ is on sys.path because tests/conftest.py lives there.)
"""

from __future__ import annotations

import contextlib
import io
import os
import queue
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import IO
from unittest import mock

from xmalign.cli import main

ROOT = Path(__file__).resolve().parents[1]
#: A wide terminal (one message per line) and this checkout's packages first.
PROCESS_ENV = {**os.environ, "COLUMNS": "200", "PYTHONPATH": str(ROOT)}
#: Served devices and the host under test stand for a unit's firmware and a PC of their own;
#: here they share two cores with the suite's other workers. As root (CI) they run ahead
#: of those (nice -10), so a busy suite does not hold a heartbeat past the units' 500 ms
#: watchdog: the timing a real setup has, not a looser test.
AHEAD = ("nice", "-n", "-10") if os.geteuid() == 0 and shutil.which("nice") else ()


def run_cli(
    *args: str, cwd: Path | None = None, timeout: float = 120
) -> subprocess.CompletedProcess:
    """Run ``xmalign ARGS`` as a user would, in a fresh interpreter."""
    return subprocess.run(
        [sys.executable, "-m", "xmalign", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=timeout,
        stdin=subprocess.DEVNULL,
    )


def assert_one_line_error(result: subprocess.CompletedProcess, *fragments: str) -> None:
    """Exit code 2, one line on stderr naming the fragments, no traceback."""
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


def run_in_process(
    *args: str, stdin: IO[str] | None = None, stdout: io.StringIO | None = None
) -> subprocess.CompletedProcess:
    """``xmalign ARGS`` in this process (quicker than a new interpreter; coverage sees it).

    ``stdin`` stands in for the terminal's input, ``stdout`` collects what is shown.
    """
    stdout = stdout if stdout is not None else io.StringIO()
    stderr = io.StringIO()
    with contextlib.ExitStack() as stack:
        stack.enter_context(mock.patch.object(sys, "argv", ["xmalign", *args]))
        if stdin is not None:
            stack.enter_context(mock.patch.object(sys, "stdin", stdin))
        stack.enter_context(contextlib.redirect_stdout(stdout))
        stack.enter_context(contextlib.redirect_stderr(stderr))
        try:
            main()
            code = 0
        except SystemExit as exit_:
            code = exit_.code
    return subprocess.CompletedProcess(args, code, stdout.getvalue(), stderr.getvalue())


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on (yet)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class Process:
    """An ``xmalign`` process whose output lines are collected as they come (``wait_for`` one)."""

    def __init__(self, args: list[str], cwd: Path, stdin: int | None = None) -> None:
        self.popen = subprocess.Popen(
            [*AHEAD, sys.executable, "-m", "xmalign", *args],
            cwd=cwd,
            stdin=stdin if stdin is not None else subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=PROCESS_ENV,
        )
        self.lines: list[str] = []
        self._t0 = time.monotonic()
        self.timed: list[str] = []  # the lines with the seconds since the start (messages)
        self._new: queue.Queue[str] = queue.Queue()
        self.stderr = ""
        threading.Thread(target=self._read, daemon=True).start()
        threading.Thread(target=self._read_stderr, daemon=True).start()

    def _read(self) -> None:
        assert self.popen.stdout is not None
        for line in self.popen.stdout:
            self.lines.append(line)
            self.timed.append(f"[{time.monotonic() - self._t0:7.2f} s] {line}")
            self._new.put(line)

    def _read_stderr(self) -> None:
        assert self.popen.stderr is not None
        self.stderr = self.popen.stderr.read()

    def said(self) -> str:
        """Everything the process said so far, each line after its time since the start."""
        return "".join(self.timed) + self.stderr

    def wait_for(self, text: str, timeout_s: float = 60.0) -> str:
        """The next output line (after those already waited for) that holds ``text``."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                line = self._new.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise AssertionError(f"no '{text}' within {timeout_s} s:\n{self.said()}") from None
            if text in line:
                return line

    def wait_for_all(self, *texts: str, timeout_s: float = 60.0) -> None:
        """The next output lines until each text was in one of them, in any order (lines
        written by different threads of the process come in either order)."""
        missing = set(texts)
        while missing:
            line = self.next_line(timeout_s)
            if line is None:
                raise AssertionError(f"ended without {missing}:\n{self.said()}")
            missing = {text for text in missing if text not in line}

    def next_line(self, timeout_s: float = 60.0) -> str | None:
        """The next output line; None once the process has ended and said everything."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                return self._new.get(timeout=0.2)
            except queue.Empty:
                if self.popen.poll() is not None and self._new.empty():
                    time.sleep(0.2)  # the reader takes the last lines
                    if self._new.empty():
                        return None
        raise AssertionError(f"no output within {timeout_s} s:\n{self.said()}")

    def finish(self, timeout_s: float = 60.0) -> int:
        code = self.popen.wait(timeout=timeout_s)
        time.sleep(0.1)  # the readers take the last lines
        return code

    def stop(self) -> None:
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGINT)
            try:
                self.popen.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait()
