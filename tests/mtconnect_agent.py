"""A small MTConnect agent for the tests: an http.server on 127.0.0.1 serving documents.

The documents are the reference agent's own sample responses (tests/firmware_iface/
data/mtconnect/, each names its source); the agent fills in the position of a
machine the test moves, the Execution, ControllerMode and Program, and the timestamps
(an observation's timestamp changes only when its value does, as an agent records them).
"""

from __future__ import annotations

import re
import threading
import time
from datetime import UTC, datetime, timedelta
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from cli_helpers import free_port

DATA = Path(__file__).parent / "firmware_iface" / "data" / "mtconnect"
AXES = ("X", "Y", "Z")
#: The Program each set of documents reports until the test sets another.
PROGRAMS = {"linuxcnc": "/home/mtconnect/simulator/spiral.ngc", "vmc_inch": "O1234"}


def stamp(moment: datetime) -> str:
    return moment.isoformat(timespec="microseconds").replace("+00:00", "Z")


class TestAgent:
    """Serves ``/probe``, ``/current`` (and ``/<device>/…``) of one machine.

    Parameters
    ----------
    documents : str
        ``linuxcnc`` or ``vmc_inch`` (files ``<documents>_probe.xml``, ``_current.xml``).
    devices : sequence of str
        The device names and uuids the documents describe.
    """

    __test__ = False  # not a pytest test class

    def __init__(self, documents: str, *devices: str) -> None:
        self.probe = (DATA / f"{documents}_probe.xml").read_text(encoding="utf-8")
        self.current = (DATA / f"{documents}_current.xml").read_text(encoding="utf-8")
        self.error = (DATA / "linuxcnc_error.xml").read_text(encoding="utf-8")
        self.devices = set(devices)
        self.values = {axis: 0.0 for axis in AXES}
        self.changed = dict.fromkeys(AXES, datetime.now(UTC))
        self.execution = "READY"
        self.mode = "AUTOMATIC"
        self.program = PROGRAMS[documents]
        #: Adapters that send unchanged values again: every timestamp is "now".
        self.repeat_unchanged = False
        #: A path's body replaced (damaged documents), and a delay before answering.
        self.replaced: dict[str, bytes] = {}
        self.delay_s = 0.0
        self.requests: list[str] = []
        self.port = free_port()
        self._server = ThreadingHTTPServer(("127.0.0.1", self.port), self._handler())
        self._server.daemon_threads = True
        self._thread = threading.Thread(target=self._server.serve_forever, daemon=True)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self) -> TestAgent:
        self._thread.start()
        return self

    def stop(self) -> None:
        if self._thread.is_alive():
            self._server.shutdown()
        self._server.server_close()

    def set(self, **values: float) -> None:
        """Set axis values (in the documents' unit); a changed one gets a new timestamp."""
        for axis, value in values.items():
            if value != self.values[axis]:
                self.changed[axis] = datetime.now(UTC)
            self.values[axis] = value

    def drop_program(self) -> None:
        """Serve a /probe without the PROGRAM data item (a device that does not report it)."""
        without = re.sub(r'\n\s*<DataItem [^>]*type="PROGRAM" ?/>', "", self.probe)
        assert without != self.probe, "the documents have no PROGRAM data item"
        self.replaced["/probe"] = without.encode()

    def age(self, seconds: float) -> None:
        """Make every axis's last change ``seconds`` old."""
        for axis in AXES:
            self.changed[axis] = datetime.now(UTC) - timedelta(seconds=seconds)

    def render(self, path: str) -> tuple[int, bytes]:
        now = datetime.now(UTC)
        parts = path.strip("/").split("/")
        if len(parts) == 2 and parts[0] not in self.devices:
            body = self.error.format(now=stamp(now), device=parts[0])
            return 404, body.encode()
        if parts[-1] == "probe":
            return 200, self.probe.encode()
        if parts[-1] != "current":
            return 404, self.error.format(now=stamp(now), device=path).encode()
        fields = {
            "now": stamp(now),
            "execution": self.execution,
            "mode": self.mode,
            "program": self.program,
            **{axis: repr(float(self.values[axis])) for axis in AXES},
            **{
                f"{axis}_time": stamp(now if self.repeat_unchanged else self.changed[axis])
                for axis in AXES
            },
        }
        return 200, self.current.format(**fields).encode()

    def _handler(self) -> type[BaseHTTPRequestHandler]:
        agent = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:  # noqa: N802 (http.server's name)
                path = self.path.split("?", 1)[0]
                agent.requests.append(path)
                time.sleep(agent.delay_s)
                status, body = (
                    (200, agent.replaced[path]) if path in agent.replaced else agent.render(path)
                )
                self.send_response(status)
                self.send_header("Content-Type", "text/xml")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, format: str, *args: object) -> None:
                pass

        return Handler
