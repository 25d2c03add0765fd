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
from sim.clock import LockstepClock
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
    lockstep : LockstepClock, optional
        The virtual clock the interferometer shares with its host in this
        process: while streaming, each wait for a sample the host announces on
        it advances it by one sample period and gets that sample (the host's
        readings are those of the in-process interferometer). Default: samples
        on the wall clock.
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
        self._sample_lock = threading.RLock()
        #: Lockstep: the host's waits for a sample answered (or dropped) so far.
        self._answered = 0
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
            if self.lockstep is not None:  # the host waits for samples only after the reply
                self._answered = self.lockstep.stream_waits()
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
            with self._sample_lock:  # lockstep: read and answer before the next sample
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

    def _serve_lockstep(self) -> None:
        """Send one sample for each wait the host announces; time reaches it as it is sent.

        The host says it waits for a streamed sample through its clock
        (``Clock.await_stream``) before each wait; this advances the virtual time by
        one sample period and sends the sample of that moment. A host that has enough
        sends STREAM OFF instead of waiting, so no sample is sent that it skips: an
        average of n samples takes n periods of virtual time, as in-process, and the
        host sees the same samples at the same virtual times however the threads run.
        """
        assert self.lockstep is not None
        clock = self.lockstep
        while not self._stop.is_set():
            if not clock.wait_for_stream_request(self._answered, _POLL_S):
                continue
            with self._sample_lock:
                waits = clock.stream_waits()
                if waits <= self._answered:  # a STREAM ON meanwhile dropped an earlier wait
                    continue
                if not self.streaming or self._stop.is_set():
                    # a wait with the stream off: nothing comes, as from the instrument
                    self._answered = waits
                    continue
                self._answered += 1
                clock.sleep(1.0 / self.rate_hz)
                self._send(encode_sample(self.interferometer.read()))
