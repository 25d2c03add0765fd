"""The simulated interferometer served on a pseudo-terminal (docs/serial-protocol.md).

The server owns the pty's master side; a client opens :attr:`PtyInterferometerServer.port`
(the slave device, e.g. ``/dev/pts/7``) with pyserial.
"""

from __future__ import annotations

import array
import fcntl
import os
import select
import termios
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
from sim.clock import LockstepClock
from xmalign.errors import FormatError
from xmalign.roles import Interferometer

IDENTIFICATION = "XMALIGN-SIM XM-60 class 1.0"
_POLL_S = 0.05
_MAX_LATE_S = 0.25
#: Lockstep: how often to look whether the host has read the last sample, and how long to
#: wait after it has before the next sample (wall time).
_LOCKSTEP_POLL_S = 50e-6
_LOCKSTEP_GRACE_S = 300e-6


class PtyInterferometerServer:
    """Serve an ``Interferometer`` on a new pty from a background thread.

    Parameters
    ----------
    interferometer : Interferometer
        Usually a :class:`sim.interferometer.SimInterferometer` on a real-time clock.
    rate_hz : float
        Initial stream rate.
    lockstep : LockstepClock, optional
        The virtual clock the interferometer shares with its host in this
        process: while streaming, each sample advances it by one sample period,
        once the host has read the previous one (the host's readings are those
        of the in-process interferometer). Default: samples on the wall clock.
    """

    def __init__(
        self,
        interferometer: Interferometer,
        rate_hz: float = 50.0,
        lockstep: LockstepClock | None = None,
    ) -> None:
        self.interferometer = interferometer
        self.rate_hz = rate_hz
        self.lockstep = lockstep
        self._streaming = threading.Event()
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.port = os.ttyname(self._slave)
        self._stop = threading.Event()
        self._write_lock = threading.Lock()
        #: Lockstep: a command and a sample (advance, read, send) never interleave, so no
        #: sample of one stream arrives after the reply that ends it.
        self._sample_lock = threading.Lock()
        self._threads = [
            threading.Thread(target=self._serve_commands, name="xm-commands", daemon=True),
            threading.Thread(
                target=self._serve_stream if lockstep is None else self._serve_lockstep,
                name="xm-stream",
                daemon=True,
            ),
        ]

    @property
    def streaming(self) -> bool:
        return self._streaming.is_set()

    @streaming.setter
    def streaming(self, on: bool) -> None:
        if on:
            self._streaming.set()
        else:
            self._streaming.clear()

    def start(self) -> None:
        for thread in self._threads:
            thread.start()

    def stop(self) -> None:
        """Stop both threads and close the pty."""
        self._stop.set()
        self._streaming.set()  # wakes a lockstep stream waiting for STREAM ON
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
        with self._sample_lock:  # a lockstep sample is sent whole before or after it
            self._handle(line)

    def _handle(self, line: bytes) -> None:
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

    def _unread_bytes(self) -> int:
        """Bytes sent that the client has not read yet."""
        count = array.array("i", [0])
        fcntl.ioctl(self._slave, termios.FIONREAD, count)
        return count[0]

    def _serve_lockstep(self) -> None:
        """Send the next sample, one period of virtual time later, once the host read the last.

        The short wait after the host has read lets a STREAM OFF that follows the
        host's last sample arrive before virtual time moves on.
        """
        assert self.lockstep is not None
        while not self._stop.is_set():
            self._streaming.wait()
            if self._unread_bytes():
                time.sleep(_LOCKSTEP_POLL_S)
                continue
            time.sleep(_LOCKSTEP_GRACE_S)
            with self._sample_lock:
                if self._stop.is_set() or not self.streaming or self._unread_bytes():
                    continue
                self.lockstep.sleep(1.0 / self.rate_hz)
                self._send(encode_sample(self.interferometer.read()))
