"""The simulated interferometer served on a pseudo-terminal (docs/serial-protocol.md).

The server owns the pty's master side; a client opens :attr:`PtyInterferometerServer.port`
(the slave device, e.g. ``/dev/pts/7``) with pyserial.
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty

from firmware_iface.xm_line_protocol import (
    Command,
    Reply,
    encode_reply,
    encode_sample,
    parse_command,
    rate_hz,
)
from xmalign.errors import FormatError
from xmalign.roles import Interferometer

IDENTIFICATION = "XMALIGN-SIM XM-60 class 1.0"
_POLL_S = 0.05
_MAX_LATE_S = 0.25


class PtyInterferometerServer:
    """Serve an ``Interferometer`` on a new pty from a background thread.

    Parameters
    ----------
    interferometer : Interferometer
        Usually a :class:`sim.interferometer.SimInterferometer` on a real-time clock.
    rate_hz : float
        Initial stream rate.
    """

    def __init__(self, interferometer: Interferometer, rate_hz: float = 50.0) -> None:
        self.interferometer = interferometer
        self.rate_hz = rate_hz
        self.streaming = False
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.port = os.ttyname(self._slave)
        self._stop = threading.Event()
        self._write_lock = threading.Lock()
        self._threads = [
            threading.Thread(target=self._serve_commands, name="xm-commands", daemon=True),
            threading.Thread(target=self._serve_stream, name="xm-stream", daemon=True),
        ]

    def start(self) -> None:
        for thread in self._threads:
            thread.start()

    def stop(self) -> None:
        """Stop both threads and close the pty."""
        self._stop.set()
        for thread in self._threads:
            if thread.is_alive():
                thread.join(2.0)
        os.close(self._master)
        os.close(self._slave)

    def _send(self, data: bytes) -> None:
        with self._write_lock:
            os.write(self._master, data)

    def handle(self, line: bytes) -> None:
        """Execute one command line and send the answer."""
        try:
            command = parse_command(line)
        except FormatError as error:
            self._send(encode_reply(Reply(False, str(error))))
            return
        self._send(encode_reply(Reply(True, self._execute(command))))
        if command.name == "READ":
            self._send(encode_sample(self.interferometer.read()))

    def _execute(self, command: Command) -> str:
        if command.name == "ID?":
            return f"ID {IDENTIFICATION}"
        if command.name == "ZERO":
            self.interferometer.zero()
        elif command.name == "STREAM":
            self.streaming = command.argument == "ON"
            return f"STREAM {command.argument}"
        elif command.name == "RATE":
            self.rate_hz = rate_hz(command.argument)
        if command.name in ("RATE", "RATE?"):
            return f"RATE {self.rate_hz:g}"
        return command.name

    def _serve_commands(self) -> None:
        buffer = b""
        while not self._stop.is_set():
            ready, _, _ = select.select([self._master], [], [], _POLL_S)
            if not ready:
                continue
            try:
                buffer += os.read(self._master, 1024)
            except OSError:  # the client side went away; keep serving for the next one
                continue
            *lines, buffer = buffer.split(b"\n")
            for line in lines:
                if line.strip():
                    self.handle(line)

    def _serve_stream(self) -> None:
        """Send samples on a fixed schedule, so a busy computer does not lower the rate."""
        next_s = time.monotonic()
        while True:
            next_s += 1.0 / self.rate_hz
            late_s = time.monotonic() - next_s
            if late_s > _MAX_LATE_S:  # far behind: start afresh rather than send a burst
                next_s = time.monotonic()
            if self._stop.wait(max(0.0, next_s - time.monotonic())):
                return
            if self.streaming:
                self._send(encode_sample(self.interferometer.read()))
