"""The linuxcncrsh driver against scripted sessions and a TCP server of our own.

The replies are those of LinuxCNC 2.9 (Debian ``linuxcnc-uspace``) as seen on a
headless instance (``man linuxcncrsh`` for the commands; the line ends ``\\r\\n``
after ``get`` and ``\\n\\r`` after ``set`` are LinuxCNC's own). The real
LinuxCNC runs in tests/linuxcnc/test_unattended_run.py.
"""

from __future__ import annotations

import logging
import socket
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from scripted import ExpectedRshLines

from firmware_iface.config import load_units_config
from firmware_iface.linuxcncrsh import LinuxCnc, LinuxcncrshLink, masked, open_linuxcnc
from sim.clock import SimClock
from sim.cnc import SimulatedCnc
from sim.servers.linuxcncrsh import LinuxcncrshServer
from xmalign.errors import (
    DeviceError,
    DeviceTimeoutError,
    DriveFaultError,
    InputError,
    TransportError,
)
from xmalign.machine import Machine
from xmalign.roles import ProgramControl, WallClock

HELLO = [
    ("hello EMC xmalign 1.0", "HELLO ACK EMCNETSVR 1.1"),
    ("set echo off", "set echo off"),
    ("set verbose on", "SET VERBOSE ACK"),
    ("set enable EMCTOO", "SET ENABLE ACK"),
    ("get user_linear_units", "USER_LINEAR_UNITS MM"),
]


def _cnc(link: ExpectedRshLines, start_timeout_s: float = 5.0) -> LinuxCnc:
    return LinuxCnc(link, 3, 0.002, SimClock(), start_timeout_s)


def test_a_session_says_hello_turns_echo_off_and_enables_control() -> None:
    with ExpectedRshLines(HELLO) as link:
        cnc = _cnc(link)
        cnc.open("EMC", "EMCTOO")
    assert isinstance(cnc, ProgramControl)


def test_a_wrong_password_is_one_clear_error() -> None:
    with (
        ExpectedRshLines([("hello nope xmalign 1.0", "HELLO NAK")]) as link,
        pytest.raises(DeviceError, match="refused the connect password"),
    ):
        _cnc(link).open("nope", None)
    steps = [*HELLO[:3], ("set enable WRONG", "SET ENABLE NAK")]
    with (
        ExpectedRshLines(steps) as link,
        pytest.raises(DeviceError, match="refused the enable password") as error,
    ):
        _cnc(link).open("EMC", "WRONG")
    assert "WRONG" not in str(error.value)


def test_an_http_server_is_named_for_what_it_is_not_a_wrong_password() -> None:
    """Issue 32: a web server on the port was reported as a wrong connect password."""
    from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

    with ThreadingHTTPServer(("127.0.0.1", 0), BaseHTTPRequestHandler) as server:
        serving = threading.Thread(target=server.serve_forever, daemon=True)
        serving.start()
        link = LinuxcncrshLink("127.0.0.1", server.server_address[1], 5.0)
        try:
            with pytest.raises(DeviceError, match="does not speak linuxcncrsh") as error:
                _cnc(link).open("EMC", None)
        finally:
            link.close()
            server.shutdown()
    assert "answered '<!DOCTYPE HTML>'" in str(error.value)  # http.server's HTTP/0.9 reply
    assert "password" not in str(error.value) and "EMC" not in str(error.value)
    with (
        ExpectedRshLines([("hello EMC xmalign 1.0", "HTTP/1.1 400 Bad Request")]) as scripted,
        pytest.raises(DeviceError, match="linuxcncrsh: answered 'HTTP/1.1 400 Bad Request'"),
    ):
        _cnc(scripted).open("EMC", None)


def test_position_is_abs_act_pos_and_standstill_needs_a_still_command_and_in_position() -> None:
    values = "100.000000 200.000000 -50.000000 0.000000 0.000000 0.000000"
    moving = "100.100000 200.000000 -50.000000 0.000000 0.000000 0.000000"
    off = "100.003000 200.000000 -50.000000 0.000000 0.000000 0.000000"
    steps = [
        ("get abs_act_pos", f"ABS_ACT_POS {values}"),
        ("get abs_cmd_pos", f"ABS_CMD_POS {values}"),
        ("get abs_cmd_pos", f"ABS_CMD_POS {moving}"),
        ("get abs_cmd_pos", f"ABS_CMD_POS {values}"),
        ("get abs_cmd_pos", f"ABS_CMD_POS {values}"),
        ("get abs_act_pos", f"ABS_ACT_POS {off}"),
        ("get abs_cmd_pos", f"ABS_CMD_POS {values}"),
        ("get abs_cmd_pos", f"ABS_CMD_POS {values}"),
        ("get abs_act_pos", f"ABS_ACT_POS {values}"),
    ]
    with ExpectedRshLines(steps) as link:
        cnc = _cnc(link)
        assert np.array_equal(cnc.position_mm(), [100.0, 200.0, -50.0])
        assert not cnc.is_standstill()  # the command moved
        assert not cnc.is_standstill()  # 3 µm from the command: not in position
        assert cnc.is_standstill()


def test_program_control_and_state() -> None:
    steps = [
        ("set mode auto", "SET MODE ACK"),
        ("set open /cnc/run.ngc", "SET OPEN ACK"),
        ("get program", "PROGRAM /cnc/old.ngc"),  # the status lags the command
        ("get error", "ERROR OK"),
        ("get program", "PROGRAM /cnc/run.ngc"),
        ("set run", "SET RUN ACK"),
        ("get program_status", "PROGRAM_STATUS IDLE"),
        ("get program_status", "PROGRAM_STATUS RUNNING"),
        ("set pause", "SET PAUSE ACK"),
        ("get program_status", "PROGRAM_STATUS PAUSED"),
        ("set resume", "SET RESUME ACK"),
        ("set abort", "SET ABORT ACK"),
        ("get program", "PROGRAM /cnc/run.ngc"),
    ]
    with ExpectedRshLines(steps) as link:
        cnc = _cnc(link)
        cnc.start_program("/cnc/run.ngc")
        cnc.hold()
        assert cnc.program_state() == "paused"
        cnc.resume()
        cnc.stop_program()
        assert cnc.loaded_program() == "/cnc/run.ngc"


def test_a_refused_command_says_linuxcncs_own_reason() -> None:
    steps = [
        ("set mode auto", "SET MODE NAK"),
        ("get error", "ERROR can't do that in estop"),
    ]
    with (
        ExpectedRshLines(steps) as link,
        pytest.raises(DeviceError, match="refused 'set mode auto'.*can't do that in estop"),
    ):
        _cnc(link).start_program("/x.ngc")


def test_a_program_linuxcnc_cannot_open_is_never_run() -> None:
    """LinuxCNC 2.9 acknowledges ``set open`` of a missing file, keeps its old program
    open, and a ``set run`` would run that one (seen in tests/linuxcnc)."""
    steps = [
        ("set mode auto", "SET MODE ACK"),
        ("set open /x.ngc", "SET OPEN ACK"),
        ("get program", "PROGRAM /cnc/old.ngc"),
        ("get error", "ERROR Unable to open file </x.ngc>"),
    ]
    with (
        ExpectedRshLines(steps) as link,
        pytest.raises(
            DeviceError,
            match=r"did not open /x.ngc \(Unable to open file </x.ngc>\); it has /cnc/old.ngc open",
        ),
    ):
        _cnc(link).start_program("/x.ngc")


def test_a_program_that_does_not_start_is_one_error() -> None:
    steps = [
        ("set mode auto", "SET MODE ACK"),
        ("set open /x.ngc", "SET OPEN ACK"),
        ("get program", "PROGRAM /x.ngc"),
        ("set run", "SET RUN ACK"),
        *[("get program_status", "PROGRAM_STATUS IDLE")] * 2,
        ("get error", "ERROR Unable to read file </x.ngc>"),
    ]
    with (
        ExpectedRshLines(steps) as link,
        pytest.raises(DeviceError, match="did not start /x.ngc .Unable to read file"),
    ):
        _cnc(link, start_timeout_s=0.02).start_program("/x.ngc")


@pytest.mark.parametrize(
    ("replies", "fragment"),
    [
        (["ESTOP ON"], "E-stop is pressed; release it"),
        (["ESTOP OFF", "MACHINE OFF"], "the machine is off; switch it on"),
        (["ESTOP OFF", "MACHINE ON", "JOINT_HOMED YES NO YES NO NO NO"], "not every joint"),
        (
            [
                "ESTOP OFF",
                "MACHINE ON",
                "JOINT_HOMED YES YES YES NO NO NO",
                "JOINT_FAULT OK FAULT OK",
            ],
            "joint fault",
        ),
    ],
)
def test_a_machine_not_ready_is_refused(replies: list[str], fragment: str) -> None:
    requests = ["get estop", "get machine", "get joint_homed", "get joint_fault"]
    with (
        ExpectedRshLines(list(zip(requests, replies, strict=False))) as link,
        pytest.raises(DriveFaultError, match=fragment),
    ):
        _cnc(link).check_ready()


def test_a_reply_to_another_question_is_refused() -> None:
    """linuxcncrsh 2.9 can garble a command when two sessions talk at once (seen)."""
    with (
        ExpectedRshLines(
            [("set resume", "SET ABS_ACT_POS NAK"), ("get error", "ERROR OK")]
        ) as link,
        pytest.raises(DeviceError, match="refused 'set resume' .SET ABS_ACT_POS NAK"),
    ):
        _cnc(link).resume()


@pytest.mark.parametrize(
    ("line", "shown"),
    [
        ("hello s3cret xmalign 1.0", "hello **** xmalign 1.0"),
        ("set enable s3cret", "set enable ****"),
        ("SET ENABLE s3cret", "SET ENABLE ****"),
        ("hello s3 cret xmalign 1.0", "hello **** xmalign 1.0"),
        ("set enable s3 cret", "set enable ****"),
        ("hello s3cret", "hello ****"),
        ("set enable off", "set enable off"),
        ("get abs_act_pos", "get abs_act_pos"),
    ],
)
def test_passwords_are_masked(line: str, shown: str) -> None:
    assert masked(line) == shown


class Server:
    """A one-connection TCP server answering each request line from a table (as
    linuxcncrsh ends its lines: ``\\r\\n`` for get, ``\\n\\r`` for set)."""

    def __init__(self, answers: dict[str, bytes]) -> None:
        self.answers = answers
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        connection, _ = self.listener.accept()
        with connection, connection.makefile("rb") as lines:
            for raw in lines:
                answer = self.answers.get(raw.decode().strip())
                if answer is None:
                    return  # an unknown request: the cable is pulled
                if answer:
                    connection.sendall(answer)


@pytest.fixture
def server() -> Iterator[Server]:
    served = Server(
        {
            "hello pw1 xmalign 1.0": b"HELLO ACK EMCNETSVR 1.1\r\n",
            "set echo off": b"set echo off\r\n",
            "set verbose on": b"SET VERBOSE ACK\n\r",
            "set enable pw2": b"SET ENABLE ACK\n\r",
            "get user_linear_units": b"USER_LINEAR_UNITS MM\r\n",
            "get abs_act_pos": b"ABS_ACT_POS 1.5 2.5 -3.5 0 0 0\r\n",
            "get program_status": b"",  # never answered
        }
    )
    yield served
    served.listener.close()


def test_over_tcp_with_linuxcncrsh_line_ends_and_passwords_never_logged(
    server: Server, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG, logger="firmware_iface")
    cnc = open_linuxcnc("127.0.0.1", server.port, 0.5, "pw1", "pw2")
    assert np.array_equal(cnc.position_mm(), [1.5, 2.5, -3.5])
    with pytest.raises(DeviceTimeoutError, match="did not answer 'get program_status'"):
        cnc.program_state()
    assert np.array_equal(cnc.position_mm(), [1.5, 2.5, -3.5])  # the session goes on
    with pytest.raises(TransportError, match="closed"):
        cnc.commanded_mm()  # not in the table: the server hangs up
    log = caplog.text
    assert "pw1" not in log and "pw2" not in log
    assert "> 'hello **** xmalign 1.0'" in log and "> 'set enable ****'" in log
    assert "< 'ABS_ACT_POS 1.5 2.5 -3.5 0 0 0'" in log


def test_a_refused_connection_is_one_line() -> None:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    with pytest.raises(TransportError, match=f"cannot connect to LinuxCNC at 127.0.0.1:{port}"):
        LinuxcncrshLink("127.0.0.1", port, 0.5)


@pytest.mark.parametrize(("units", "mm_per_unit"), [("MM", 1.0), ("INCH", 25.4), ("CM", 10.0)])
def test_positions_come_in_mm_whatever_the_machines_units(units: str, mm_per_unit: float) -> None:
    """linuxcncrsh prints ``abs_act_pos`` in [TRAJ] LINEAR_UNITS (emcrsh.cc, LinuxCNC 2.9:
    ``emcStatus->motion.traj.actualPosition`` unconverted; its ``set
    linear_unit_conversion`` converts only offsets: seen on the real one in
    tests/linuxcnc/test_mdi_moves.py)."""
    steps = [
        *HELLO[:4],
        ("get user_linear_units", f"USER_LINEAR_UNITS {units}"),
        ("get abs_act_pos", "ABS_ACT_POS 1.000000 2.000000 -0.500000 0.000000 0.000000 0.000000"),
    ]
    with ExpectedRshLines(steps) as link:
        cnc = _cnc(link)
        cnc.open("EMC", "EMCTOO")
        assert np.allclose(cnc.position_mm(), np.array([1.0, 2.0, -0.5]) * mm_per_unit)


def test_a_machine_in_custom_units_is_refused() -> None:
    steps = [*HELLO[:4], ("get user_linear_units", "USER_LINEAR_UNITS CUSTOM")]
    with (
        ExpectedRshLines(steps) as link,
        pytest.raises(DeviceError, match="linear units are CUSTOM"),
    ):
        _cnc(link).open("EMC", "EMCTOO")


def test_an_mdi_move_states_mm_absolute_and_feed_per_minute() -> None:
    """On an inch machine (or after a G20, G91, G93) a bare ``G53 G1 X10`` is not 10 mm."""
    at = "ABS_ACT_POS 0.393701 0.787402 -0.196850 0.000000 0.000000 0.000000"
    at_cmd = at.replace("ABS_ACT_POS", "ABS_CMD_POS")
    steps = [
        *HELLO[:4],
        ("get user_linear_units", "USER_LINEAR_UNITS INCH"),
        ("get program_status", "PROGRAM_STATUS IDLE"),
        ("set mode mdi", "SET MODE ACK"),
        ("get error", "ERROR OK"),
        ("set mdi G21 G90 G94 G53 G1 X10.0000 Y20.0000 Z-5.0000 F600.0", "SET MDI ACK"),
        ("get program_status", "PROGRAM_STATUS IDLE"),
        ("get abs_cmd_pos", at_cmd),
        ("get abs_cmd_pos", at_cmd),
        ("get abs_act_pos", at),
        ("get abs_act_pos", at),
    ]
    with ExpectedRshLines(steps) as link:
        cnc = _cnc(link)
        cnc.open("EMC", "EMCTOO")
        cnc.move_mdi(np.array([10.0, 20.0, -5.0]), 600.0, 0.005, 10.0)


def test_an_mdi_move_is_aborted_when_the_wait_ends_early() -> None:
    """An error or Ctrl-C while the machine moves: ``set abort`` before it propagates."""
    steps = [
        ("get program_status", "PROGRAM_STATUS IDLE"),
        ("set mode mdi", "SET MODE ACK"),
        ("get error", "ERROR OK"),
        ("set mdi G21 G90 G94 G53 G1 X10.0000 Y20.0000 Z-5.0000 F600.0", "SET MDI ACK"),
        ("get program_status", KeyboardInterrupt()),
        ("set abort", "SET ABORT ACK"),
    ]
    with ExpectedRshLines(steps) as link, pytest.raises(KeyboardInterrupt):
        _cnc(link).move_mdi(np.array([10.0, 20.0, -5.0]), 600.0, 0.005, 10.0)


@pytest.mark.parametrize("password", ["pw 1", "pw\t1", "", "pässword"])
def test_a_password_linuxcncrsh_cannot_take_is_refused_before_it_is_sent(password: str) -> None:
    """linuxcncrsh splits each request on spaces and tabs (emcrsh.cc, ``toksep``): a
    password with a space could never match, and would be sent in parts."""
    with ExpectedRshLines([]) as link, pytest.raises(InputError, match="one word") as error:
        _cnc(link).open(password or "EMC", password)
    assert password not in str(error.value) or not password


def test_the_wire_log_and_a_timeout_never_show_a_spaced_password(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A password with a space must not leak its tail: the whole argument is masked."""
    caplog.set_level(logging.DEBUG, logger="firmware_iface")
    with socket.create_server(("127.0.0.1", 0)) as listener:
        link = LinuxcncrshLink("127.0.0.1", listener.getsockname()[1], 0.05)
        with pytest.raises(DeviceTimeoutError) as error:
            link.ask("hello top secret xmalign 1.0")
        link.close()
    assert "secret" not in str(error.value) and "'hello **** xmalign 1.0'" in str(error.value)
    assert "secret" not in caplog.text and "top" not in caplog.text


def test_the_documented_example_loads_and_is_in_the_docs(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    root = Path(__file__).resolve().parents[2]
    example = root / "examples" / "units-linuxcncrsh.yaml"
    config = load_units_config(example)
    rsh = config.machine_position.linuxcncrsh
    assert rsh is not None and config.machine_position.controlled is rsh
    assert (rsh.timeout_s, rsh.start_timeout_s) == (1.0, 5.0)
    monkeypatch.setenv("XMALIGN_LINUXCNC_CONNECT_PW", "c0nnect")
    monkeypatch.setenv("XMALIGN_LINUXCNC_ENABLE_PW", "3nable")
    assert rsh.passwords() == ("c0nnect", "3nable")
    docs = (root / "docs" / "hardware.md").read_text(encoding="utf-8")
    assert example.read_text(encoding="utf-8") in docs, "docs/hardware.md lost the example"


def test_a_reply_left_by_an_interrupted_request_is_not_taken_for_the_next(
    server: Server, monkeypatch: pytest.MonkeyPatch
) -> None:
    """SIGTERM while 'set resume' waits for its reply: the next request, 'set pause', gets
    its own reply, not 'SET RESUME ACK' (seen with 2.9 before replies were matched)."""
    server.answers.update({"set resume": b"SET RESUME ACK\n\r", "set pause": b"SET PAUSE ACK\n\r"})
    cnc = open_linuxcnc("127.0.0.1", server.port, 0.5, "pw1", "pw2")
    link = cnc.link
    assert isinstance(link, LinuxcncrshLink)
    read_line = link._read_line

    def interrupted() -> str:
        monkeypatch.setattr(link, "_read_line", read_line)
        raise KeyboardInterrupt  # the signal arrives before the reply is read

    monkeypatch.setattr(link, "_read_line", interrupted)
    with pytest.raises(KeyboardInterrupt):
        cnc.resume()
    cnc.hold()  # its own reply: SET PAUSE ACK
    assert np.array_equal(cnc.position_mm(), [1.5, 2.5, -3.5])


def test_a_set_without_a_reply_while_gets_are_answered_is_a_stopped_task(
    reference_machine: Machine,
) -> None:
    """After milltask dies, linuxcncrsh answers 'get' from the status it last had and no
    'set' (seen with LinuxCNC 2.9; the simulated linuxcncrsh does the same)."""
    server = LinuxcncrshServer(SimulatedCnc(reference_machine, WallClock()), reference_machine)
    server.start()
    cnc = open_linuxcnc("127.0.0.1", server.port, 0.2)
    try:
        server.linuxcnc.kill_task()
        with pytest.raises(DeviceError) as caught:
            cnc.hold()
    finally:
        cnc.close()
        server.stop()
    assert str(caught.value) == (
        f"LinuxCNC at 127.0.0.1:{server.port} did not answer 'set pause' within 0.2 s although"
        " linuxcncrsh answers: LinuxCNC's task (milltask) has stopped; restart LinuxCNC"
    )
    assert not isinstance(caught.value, TransportError)
