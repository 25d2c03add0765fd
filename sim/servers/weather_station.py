"""The simulated weather station served on a pseudo-terminal (firmware_iface.weather_station).

Answers ``ENV?`` with an ``E`` line of the station's present reading and
``ID?`` with its identification; anything else gets an ``ERR`` line. While
the station does not answer (``station.answering`` False) queries get nothing.
"""

from __future__ import annotations

import os
import select
import threading
import tty

from firmware_iface.weather_station import encode_environment, encode_station_reply
from xmalign.errors import TransportError
from xmalign.roles import EnvironmentSource

IDENTIFICATION = "XMALIGN-SIM XC-80 class 1.0"
_POLL_S = 0.05


class PtyStationServer:
    """Serve an ``EnvironmentSource`` on a new pty (``port``) from a background thread."""

    def __init__(self, station: EnvironmentSource) -> None:
        self.station = station
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.port = os.ttyname(self._slave)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="xc-station", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2.0)
        os.close(self._master)
        os.close(self._slave)

    def answer(self, line: bytes) -> bytes:
        """The answer to one query line (empty when the station does not answer)."""
        query = line.decode("ascii", "replace").strip().upper()
        if query == "ID?":
            return encode_station_reply(True, f"ID {IDENTIFICATION}")
        if query != "ENV?":
            return encode_station_reply(False, f"unknown command {query[:20]!r}")
        try:
            return encode_environment(self.station.read())
        except TransportError:
            return b""

    def _serve(self) -> None:
        buffer = b""
        while not self._stop.is_set():
            ready, _, _ = select.select([self._master], [], [], _POLL_S)
            if not ready:
                continue
            try:
                buffer += os.read(self._master, 1024)
            except OSError:  # the client went away; keep serving the next one
                continue
            *lines, buffer = buffer.split(b"\n")
            for line in lines:
                if line.strip() and (reply := self.answer(line)):
                    os.write(self._master, reply)
