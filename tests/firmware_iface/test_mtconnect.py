"""The MTConnect position source against agent documents served on 127.0.0.1.

The documents (``mtconnect/probe.xml``, ``mtconnect/current.xml``) follow the
form of the MTConnect Institute's reference agent (github.com/mtconnect/cppagent,
``samples/test_probe.xml`` and ``samples/test_current.xml``: a device with
``Linear`` X, Y, Z carrying ``POSITION`` ``ACTUAL``/``COMMANDED`` data items and
a ``Controller`` with ``EXECUTION`` and ``CONTROLLER_MODE``), written anew with
the ``coordinateSystem`` attribute of the MTConnect standard's ``DataItem`` and
values of our own.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest

from firmware_iface.mtconnect import MTConnectAgent
from sim.clock import SimClock
from xmalign.errors import DeviceError, TransportError
from xmalign.roles import MachinePositionSource

DOCUMENTS = Path(__file__).resolve().parent / "mtconnect"
PROBE = (DOCUMENTS / "probe.xml").read_text(encoding="utf-8")
#: ``str.format`` fields: x, y, z (mm) and execution.
CURRENT = (DOCUMENTS / "current.xml").read_text(encoding="utf-8")


class Agent:
    """An HTTP server answering /probe and /current (also under /VMC/) from ``state``."""

    def __init__(self, probe: str = PROBE) -> None:
        self.probe = probe
        self.state = {"x": "100.5", "y": "200.25", "z": "-50.0", "execution": "READY"}
        self.requests: list[str] = []
        agent = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:  # noqa: N802 - the http.server name
                agent.requests.append(self.path)
                pages = {"probe": agent.probe, "current": CURRENT.format(**agent.state)}
                pages |= {f"VMC/{name}": page for name, page in pages.items()}
                request = self.path.lstrip("/")
                if request not in pages:
                    self.send_error(404)
                    return
                body = pages[request].encode()
                self.send_response(200)
                self.send_header("Content-Type", "text/xml")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *args: object) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()


@pytest.fixture
def agent() -> Iterator[Agent]:
    served = Agent()
    yield served
    served.server.shutdown()


def test_the_machine_coordinate_actual_position_and_the_program_state(agent: Agent) -> None:
    source = MTConnectAgent(agent.url, 2.0, clock=SimClock())
    assert isinstance(source, MachinePositionSource)
    assert np.array_equal(source.position_mm(), [100.5, 200.25, -50.0])  # not the WORK item
    assert source.is_standstill()
    expected = {
        "ACTIVE": "running",
        "FEED_HOLD": "paused",
        "PROGRAM_STOPPED": "paused",
        "INTERRUPTED": "paused",
        "READY": "idle",
        "STOPPED": "idle",
    }
    for execution, state in expected.items():
        agent.state["execution"] = execution
        assert source.program_state() == state
    assert source.controller_mode() == "AUTOMATIC"


def test_a_named_device_is_asked_under_its_name(agent: Agent) -> None:
    MTConnectAgent(agent.url, 2.0, device="VMC").position_mm()
    assert agent.requests == ["/VMC/probe", "/VMC/current"]


def test_an_unavailable_position_is_refused(agent: Agent) -> None:
    source = MTConnectAgent(agent.url, 2.0)
    agent.state["y"] = "UNAVAILABLE"
    with pytest.raises(DeviceError, match="position X Y Z is 100.5 UNAVAILABLE -50.0"):
        source.position_mm()


def test_an_axis_with_only_work_coordinates_is_refused() -> None:
    served = Agent(PROBE.replace('coordinateSystem="MACHINE"', 'coordinateSystem="WORK"'))
    try:
        with pytest.raises(DeviceError, match="axis X has no actual position in machine"):
            MTConnectAgent(served.url, 2.0)
    finally:
        served.server.shutdown()


def test_an_unknown_device_and_an_unreachable_agent_are_one_line(agent: Agent) -> None:
    with pytest.raises(DeviceError, match="GET /HMC/probe answered HTTP 404"):
        MTConnectAgent(agent.url, 2.0, device="HMC")
    agent.server.shutdown()
    agent.server.server_close()
    with pytest.raises(TransportError, match="cannot reach the MTConnect agent"):
        MTConnectAgent(agent.url, 1.0)
