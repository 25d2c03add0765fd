"""Two pseudo-terminals joined back to back: a null-modem cable inside the host.

A server that opens serial ports by name (pymodbus's RTU server) opens
:attr:`PtyPair.server_port`; the client opens :attr:`PtyPair.client_port`; a
thread copies the bytes between the two master sides.
"""

from __future__ import annotations

import os
import select
import threading
import tty

_POLL_S = 0.05


class PtyPair:
    """Two ptys whose slave ends talk to each other (``start``/``stop``)."""

    def __init__(self, name: str = "pty-pair") -> None:
        self._server_master, self._server_slave = os.openpty()
        self._client_master, self._client_slave = os.openpty()
        for fd in (self._server_slave, self._client_slave):
            tty.setraw(fd)
        self.server_port = os.ttyname(self._server_slave)
        self.client_port = os.ttyname(self._client_slave)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._relay, name=name, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2.0)
        for fd in (
            self._server_master,
            self._server_slave,
            self._client_master,
            self._client_slave,
        ):
            os.close(fd)

    def _relay(self) -> None:
        peer = {
            self._server_master: self._client_master,
            self._client_master: self._server_master,
        }
        while not self._stop.is_set():
            ready, _, _ = select.select(list(peer), [], [], _POLL_S)
            for fd in ready:
                try:
                    data = os.read(fd, 4096)
                except OSError:  # the other side closed its slave end; wait for the next
                    continue
                os.write(peer[fd], data)
