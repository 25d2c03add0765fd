"""MTConnect: the agent's documents as the reference agent sends them, served on 127.0.0.1.

The documents are mtconnect/cppagent's sample responses (samples/test_probe.xml,
test_current.xml, test_error.xml; simulator/VMC-3Axis.xml and the coordinate
systems of test_package/resources/samples/kinematics.xml), each file in
tests/firmware_iface/data/mtconnect/ says where it comes from and what was changed.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterator

import numpy as np
import pytest
from cli_helpers import free_port
from hypothesis import given, settings
from hypothesis import strategies as st
from mtconnect_agent import TestAgent

from firmware_iface.mtconnect import AgentLink, MTConnectMachine, open_mtconnect
from sim.clock import SimClock
from xmalign.errors import DeviceError, DeviceTimeoutError, TransportError


@pytest.fixture
def linuxcnc_agent() -> Iterator[TestAgent]:
    agent = TestAgent("linuxcnc", "LinuxCNC", "000").start()
    yield agent
    agent.stop()


@pytest.fixture
def vmc_agent() -> Iterator[TestAgent]:
    agent = TestAgent("vmc_inch", "VMC-3Axis", "000", "Lathe", "001").start()
    yield agent
    agent.stop()


def test_position_program_state_and_mode_from_the_reference_agents_documents(
    linuxcnc_agent: TestAgent,
) -> None:
    linuxcnc_agent.set(X=0.00199, Y=0.0002, Z=1.0)  # the sample's own values
    with open_mtconnect(linuxcnc_agent.url, 2.0) as machine:
        assert np.allclose(machine.position_mm(), [0.00199, 0.0002, 1.0])
        status = machine.status()
        assert (status.program_state, status.state, status.mode) == ("idle", "READY", "AUTOMATIC")
        for execution, state in [
            ("ACTIVE", "running"),
            ("FEED_HOLD", "paused"),
            ("INTERRUPTED", "paused"),
            ("PROGRAM_STOPPED", "paused"),
            ("OPTIONAL_STOP", "paused"),
            ("STOPPED", "idle"),
            ("PROGRAM_COMPLETED", "idle"),
            ("WAIT", "running"),
        ]:
            linuxcnc_agent.execution = execution
            assert machine.program_state() == state, execution
    assert linuxcnc_agent.requests[0] == "/probe"


def test_machine_positions_in_inches_are_converted_and_work_positions_never_used(
    vmc_agent: TestAgent,
) -> None:
    vmc_agent.set(X=10.0, Y=-2.5, Z=0.125)
    with open_mtconnect(vmc_agent.url, 2.0, device="VMC-3Axis") as machine:
        assert np.allclose(machine.position_mm(), [254.0, -63.5, 3.175])
    assert vmc_agent.requests == ["/VMC-3Axis/probe", "/VMC-3Axis/current"]


def test_units_declared_by_the_agent_win_over_native_units(vmc_agent: TestAgent) -> None:
    # units="MILLIMETER" nativeUnits="INCH": the agent converted already
    vmc_agent.probe = vmc_agent.probe.replace(
        'nativeUnits="INCH" subType', 'nativeUnits="INCH" units="MILLIMETER" subType'
    )
    vmc_agent.set(X=10.0)
    with open_mtconnect(vmc_agent.url, 2.0, device="000") as machine:  # by uuid
        assert machine.position_mm()[0] == pytest.approx(10.0)


@pytest.mark.parametrize(
    ("device", "axes", "message"),
    [
        (None, ("X", "Y", "Z"), "expected one device, the agent has: VMC-3Axis, Lathe"),
        (
            "Lathe",
            ("X", "Y", "Z"),
            "no actual machine POSITION of a linear axis Y (linear axes: X, Z)",
        ),
        ("VMC-3Axis", ("X", "Y", "W"), "linear axis W (linear axes: X, Y, Z)"),
    ],
)
def test_missing_devices_and_axes_are_one_line_naming_the_agent(
    vmc_agent: TestAgent, device: str | None, axes: tuple[str, str, str], message: str
) -> None:
    with pytest.raises(DeviceError, match=re.escape(message)) as caught:
        open_mtconnect(vmc_agent.url, 2.0, device=device, axes=axes)
    assert vmc_agent.url in str(caught.value) and "\n" not in str(caught.value)


def test_an_unknown_device_is_the_agents_error_document(vmc_agent: TestAgent) -> None:
    machine = open_mtconnect(vmc_agent.url, 2.0, device="VMC-3Axis")
    vmc_agent.devices.discard("VMC-3Axis")  # e.g. the agent restarted with another device file
    with pytest.raises(DeviceError, match=r"refused /current: NO_DEVICE: Could not find the dev"):
        machine.position_mm()


@pytest.mark.parametrize(
    ("body", "message"),
    [
        (b"<MTConnectStreams><Header", "damaged /current document \\(not XML at line 1"),
        (b"", "damaged /current document"),
        (b"<html><body>proxy error</body></html>", "with <html>, not <MTConnectStreams>"),
    ],
)
def test_a_damaged_document_is_one_transport_error(
    linuxcnc_agent: TestAgent, body: bytes, message: str
) -> None:
    machine = open_mtconnect(linuxcnc_agent.url, 2.0)
    linuxcnc_agent.replaced["/current"] = body
    with pytest.raises(TransportError, match=message) as caught:
        machine.position_mm()
    assert linuxcnc_agent.url in str(caught.value) and "\n" not in str(caught.value)


@pytest.mark.parametrize("text", ["NaN", "INF", "1.5mm", ""])
def test_a_position_that_is_not_a_finite_number_is_a_device_fault(
    linuxcnc_agent: TestAgent, text: str
) -> None:
    machine = open_mtconnect(linuxcnc_agent.url, 2.0)
    linuxcnc_agent.current = linuxcnc_agent.current.replace("{Y}", text, 1)
    with pytest.raises(DeviceError, match=f"the Y position '{text}' is not a number"):
        machine.position_mm()


def test_the_program_is_the_agents_program_data_item_with_its_state(
    linuxcnc_agent: TestAgent, vmc_agent: TestAgent
) -> None:
    with open_mtconnect(linuxcnc_agent.url, 2.0) as machine:
        report = machine.program_report()
        assert report is not None
        assert (report.name, report.state) == ("/home/mtconnect/simulator/spiral.ngc", "idle")
        linuxcnc_agent.program, linuxcnc_agent.execution = "/home/cnc/run.ngc", "FEED_HOLD"
        report = machine.program_report()
        assert report is not None and (report.name, report.state) == ("/home/cnc/run.ngc", "paused")
        linuxcnc_agent.program = ""  # no program loaded
        report = machine.program_report()
        assert report is not None and report.name is None
    with open_mtconnect(vmc_agent.url, 2.0, device="VMC-3Axis") as machine:
        report = machine.program_report()
        assert report is not None and report.name == "O1234"


def test_an_agent_that_does_not_report_the_program_says_so_with_none(
    linuxcnc_agent: TestAgent,
) -> None:
    """No PROGRAM data item in /probe, or its value UNAVAILABLE: the program is not reported
    (the run says so once and goes on); the position and state still are."""
    linuxcnc_agent.program = "UNAVAILABLE"
    with open_mtconnect(linuxcnc_agent.url, 2.0) as machine:
        assert machine.program_report() is None
        assert machine.status().program_state == "idle"
        linuxcnc_agent.program, linuxcnc_agent.execution = "old.ngc", "UNAVAILABLE"
        report = machine.program_report()  # the state unknown: compared as if running
        assert report is not None and (report.name, report.state) == ("old.ngc", "running")
    linuxcnc_agent.drop_program()
    with open_mtconnect(linuxcnc_agent.url, 2.0) as machine:
        assert machine.program_report() is None


def test_the_main_program_is_preferred_to_the_active_one(linuxcnc_agent: TestAgent) -> None:
    """MTConnect 1.5 on: PROGRAM with subType MAIN (the program selected) and ACTIVE (the
    one executing, a subprogram): MAIN names the program; SCHEDULE never."""
    item = (
        '<DataItem category="EVENT" id="23" name="program" significantDigits="0" type="PROGRAM" />'
    )
    assert item in linuxcnc_agent.probe
    linuxcnc_agent.replaced["/probe"] = linuxcnc_agent.probe.replace(
        item,
        item.replace('id="23"', 'id="22" subType="SCHEDULE"').replace("program", "schedule", 1)
        + item.replace('id="23"', 'id="21" subType="ACTIVE"').replace("program", "active", 1)
        + item.replace('id="23"', 'id="23" subType="MAIN"'),
    ).encode()
    with open_mtconnect(linuxcnc_agent.url, 2.0) as machine:
        report = machine.program_report()
    assert report is not None and report.name == "/home/mtconnect/simulator/spiral.ngc"


@pytest.mark.parametrize(("field", "what"), [("X", "X position"), ("execution", "Execution")])
def test_unavailable_values_are_a_device_fault(
    linuxcnc_agent: TestAgent, field: str, what: str
) -> None:
    machine = open_mtconnect(linuxcnc_agent.url, 2.0)
    linuxcnc_agent.current = linuxcnc_agent.current.replace("{" + field + "}", "UNAVAILABLE", 1)
    with pytest.raises(DeviceError, match=f"reports the {what} UNAVAILABLE"):
        machine.status()


def test_an_unreachable_agent_is_a_transport_error_naming_it() -> None:
    url = f"http://127.0.0.1:{free_port()}"
    with pytest.raises(TransportError, match=f"cannot reach the MTConnect agent at {url}"):
        open_mtconnect(url, 1.0)


def test_an_agent_that_does_not_answer_in_time_is_a_timeout(linuxcnc_agent: TestAgent) -> None:
    linuxcnc_agent.delay_s = 1.0
    with pytest.raises(DeviceTimeoutError, match=r"did not answer probe within 0.2 s"):
        open_mtconnect(linuxcnc_agent.url, 0.2)


def test_old_timestamps_alone_are_no_standstill(linuxcnc_agent: TestAgent) -> None:
    """An adapter's clock running behind the agent's makes every observation look old
    (cppagent keeps the adapter's timestamps): only positions seen unchanged for the
    settle time on xmalign's clock count."""
    linuxcnc_agent.set(X=5.0, Y=6.0, Z=7.0)
    linuxcnc_agent.age(60.0)
    clock = SimClock()
    machine = open_mtconnect(linuxcnc_agent.url, 2.0, settle_s=0.5, clock=clock)
    assert not machine.is_standstill()  # nothing seen before
    clock.sleep(0.3)
    assert not machine.is_standstill()
    clock.sleep(0.3)
    assert machine.is_standstill()


def test_standstill_from_successive_positions_within_the_tolerance(
    linuxcnc_agent: TestAgent,
) -> None:
    linuxcnc_agent.repeat_unchanged = True  # the timestamps say nothing
    clock = SimClock()
    machine = open_mtconnect(
        linuxcnc_agent.url, 2.0, settle_s=0.5, standstill_tolerance_mm=0.002, clock=clock
    )
    jitter = iter([0.0, 0.0008, -0.0008, 0.0005, 0.0, 0.0008])
    seen = []
    for _ in range(6):
        linuxcnc_agent.set(X=100.0 + next(jitter))
        seen.append(machine.is_standstill())
        clock.sleep(0.2)
    assert seen == [False, False, False, True, True, True]
    linuxcnc_agent.set(X=100.1)  # moves on
    assert not machine.is_standstill()


def test_requests_are_logged_without_anything_else(
    linuxcnc_agent: TestAgent, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG, logger="firmware_iface.mtconnect")
    with MTConnectMachine(AgentLink(linuxcnc_agent.url, 2.0)) as machine:
        machine.position_mm()
    lines = [r.getMessage() for r in caplog.records]
    assert f"the MTConnect agent at {linuxcnc_agent.url} > GET {linuxcnc_agent.url}/probe" in lines
    assert any(re.search(r"< HTTP 200, \d+ bytes$", line) for line in lines)
    assert any("machine position" in line for line in lines)


class DocumentsLink:
    """The agent's documents without HTTP: for many damaged variants, fast."""

    name = "the MTConnect agent at test://documents"

    def __init__(self, probe: bytes, current: bytes) -> None:
        self.bodies = {"probe": probe, "current": current}

    def get(self, path: str) -> tuple[int, bytes]:
        return 200, self.bodies[path]

    def close(self) -> None:
        pass


def _documents() -> tuple[bytes, bytes]:
    agent = TestAgent("linuxcnc", "LinuxCNC")
    agent.stop()  # only its documents are wanted
    agent.set(X=1.5, Y=2.5, Z=-3.5)
    return agent.probe.encode(), agent.render("/current")[1]


PROBE, CURRENT = _documents()


@settings(max_examples=150, deadline=None)
@given(
    cut=st.integers(min_value=0, max_value=len(CURRENT)),
    flips=st.lists(st.tuples(st.integers(0, len(CURRENT) - 1), st.integers(0, 255)), max_size=4),
)
def test_damaged_current_documents_give_a_position_or_one_project_error(
    cut: int, flips: list[tuple[int, int]]
) -> None:
    damaged = bytearray(CURRENT[:cut] if not flips else CURRENT)
    for at, byte in flips:
        if at < len(damaged):
            damaged[at] = byte
    machine = MTConnectMachine(DocumentsLink(PROBE, bytes(damaged))).open()
    try:
        status = machine.status()
    except (TransportError, DeviceError) as error:
        assert "test://documents" in str(error) and "\n" not in str(error)
    else:
        assert status.position_mm.shape == (3,) and np.isfinite(status.position_mm).all()
