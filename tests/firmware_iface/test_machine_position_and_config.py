"""Machine-position sources and the units.yaml configuration (opened against simulated servers)."""

from __future__ import annotations

import re
import textwrap
from pathlib import Path

import numpy as np
import pytest

from firmware_iface.config import load_units_config, open_devices
from firmware_iface.machine_position import (
    CheckedMover,
    FilePositions,
    OperatorPrompt,
    parse_position,
)
from firmware_iface.modbus import ModbusUnit
from sim.clock import SimClock
from sim.cnc import SimulatedCnc
from sim.servers.modbus import ModbusUnitServer
from sim.units import SimUnit
from xmalign.errors import (
    DeviceTimeoutError,
    FormatError,
    InputError,
    OutOfRangeError,
    TransportError,
    XmalignError,
)
from xmalign.safety import units_locked_on_exit

ROOT = Path(__file__).resolve().parents[2]


class Operator:
    """Scripted answers; records what was said."""

    def __init__(self, answers: list[str]) -> None:
        self.answers = answers
        self.told: list[str] = []

    def ask(self, prompt: str) -> str:
        if not self.answers:
            raise EOFError
        return self.answers.pop(0)

    def tell(self, message: str) -> None:
        self.told.append(message)


@pytest.mark.parametrize(
    ("text", "expected"),
    [("1 2 3", [1, 2, 3]), ("1.5,-2;3e2", [1.5, -2, 300]), ("1 2", None), ("a b c", None)],
)
def test_parse_position(text: str, expected: list[float] | None) -> None:
    result = parse_position(text)
    assert (result is None) if expected is None else np.allclose(result, expected)


def test_operator_prompt_validates_until_a_good_position(reference_machine) -> None:  # noqa: ANN001
    operator = Operator(["nonsense", "5000 0 0", "900 900 -100", "1000.2 999.9 -100.1"])
    mover = OperatorPrompt(reference_machine, operator.ask, operator.tell)
    mover.move_to([1000.0, 1000.0, -100.0], 2000.0)
    np.testing.assert_allclose(mover.position_mm(), [1000.2, 999.9, -100.1])
    assert "Move the machine to X1000.000 Y1000.000 Z-100.000" in operator.told[0]
    assert "'nonsense' is not a position" in operator.told[1]
    assert "outside the machine's travel" in operator.told[2]
    assert "more than 5 mm from the target" in operator.told[3]


def test_operator_prompt_enter_accepts_the_target_and_eof_is_an_error(reference_machine) -> None:  # noqa: ANN001
    operator = Operator([""])
    mover = OperatorPrompt(reference_machine, operator.ask, operator.tell)
    mover.move_to([10.0, 20.0, -30.0], 2000.0)
    np.testing.assert_allclose(mover.position_mm(), [10.0, 20.0, -30.0])
    with pytest.raises(XmalignError, match="no answer from the operator"):
        mover.move_to([10.0, 20.0, -40.0], 2000.0)
    with pytest.raises(OutOfRangeError, match="outside the machine's travel"):
        mover.move_to([10.0, 20.0, 40.0], 2000.0)


def test_operator_prompt_reads_the_position_from_a_file(reference_machine, tmp_path) -> None:  # noqa: ANN001
    path = tmp_path / "pos.txt"
    path.write_text("# written by the CNC\n0 0 0\n500.001, 400, -100.002\n\n")
    operator = Operator([""])
    mover = OperatorPrompt(reference_machine, operator.ask, operator.tell, FilePositions(path))
    mover.move_to([500.0, 400.0, -100.0], 2000.0)
    np.testing.assert_allclose(mover.position_mm(), [500.001, 400.0, -100.002])


def test_operator_prompt_asks_again_while_the_file_shows_the_machine_elsewhere(
    reference_machine, tmp_path
) -> None:  # noqa: ANN001
    """Enter pressed while the CNC is still on its way: the position is not taken."""
    path = tmp_path / "pos.txt"
    path.write_text("0 0 0\n")
    operator = Operator(["", ""])

    def ask(prompt: str) -> str:
        if len(operator.answers) == 1:  # the second Enter: the CNC has arrived
            path.write_text("500.002 400 -100\n")
        return operator.ask(prompt)

    mover = OperatorPrompt(reference_machine, ask, operator.tell, FilePositions(path))
    mover.move_to([500.0, 400.0, -100.0], 2000.0)
    np.testing.assert_allclose(mover.position_mm(), [500.002, 400.0, -100.0])
    assert operator.told[1] == (
        "the machine stands at X0.000 Y0.000 Z0.000, 648.1 mm from the target; move it there first"
    )
    assert not operator.answers


def test_file_positions_name_the_bad_line(tmp_path) -> None:  # noqa: ANN001
    path = tmp_path / "pos.txt"
    path.write_text("1 2 3\n1 2\n")
    with pytest.raises(FormatError, match="pos.txt: line 2: expected three numbers"):
        FilePositions(path).position_mm()


def test_checked_mover_on_the_simulated_cnc(reference_machine) -> None:  # noqa: ANN001
    clock = SimClock()
    mover = CheckedMover(
        SimulatedCnc(reference_machine, clock), reference_machine, "simulated CNC", clock=clock
    )
    mover.move_to([1200.0, 300.0, -250.0], 8000.0)
    np.testing.assert_allclose(mover.position_mm(), [1200.0, 300.0, -250.0])
    with pytest.raises(OutOfRangeError, match="outside the travel of the simulated CNC"):
        mover.move_to([1200.0, 300.0, 250.0], 8000.0)


def test_example_units_config_loads() -> None:
    config = load_units_config(ROOT / "examples" / "units.yaml")
    assert config.launch.transport == "modbus-tcp" and config.receiver.transport == "canopen"


@pytest.mark.parametrize(
    ("body", "fragment"),
    [
        ("launch: {transport: modbus-tcp, port: 502}", "key 'launch.modbus-tcp.host'"),
        ("launch: {transport: usb, host: x}", "key 'launch'"),
        (
            "launch: {transport: modbus-tcp, host: x, speed: 3}",
            "key 'launch.modbus-tcp.speed': not a known key",
        ),
        (
            "launch: {transport: canopen, interface: udp_local, channel: 999.999.1.1}",
            "key 'launch.canopen.channel': '999.999.1.1' is not an IPv4 multicast group",
        ),
        (
            "launch: {transport: canopen, interface: nosuchbus, channel: can0}",
            "key 'launch.canopen.interface': no CAN interface 'nosuchbus'",
        ),
    ],
)
def test_bad_units_config_names_file_and_key(tmp_path, body: str, fragment: str) -> None:  # noqa: ANN001
    path = tmp_path / "units.yaml"
    path.write_text(
        textwrap.dedent(f"""\
        format: xmalign.units/1
        {body}
        receiver: {{transport: modbus-tcp, host: localhost}}
        interferometer: {{port: /dev/null}}
        """)
    )
    with pytest.raises(InputError, match=f"units.yaml: .*{fragment}".replace("[", r"\[")):
        load_units_config(path)


def test_interferometer_needs_exactly_one_source(tmp_path) -> None:  # noqa: ANN001
    path = tmp_path / "units.yaml"
    path.write_text(
        "format: xmalign.units/1\nlaunch: {transport: modbus-tcp, host: a}\n"
        "receiver: {transport: modbus-tcp, host: b}\ninterferometer: {}\n"
    )
    with pytest.raises(InputError, match="key 'interferometer': give exactly one of"):
        load_units_config(path)


def test_open_devices_on_simulated_servers(
    reference_machine,
    served_launch,
    free_port,  # noqa: ANN001
    tmp_path,
) -> None:
    _, launch_server = served_launch
    receiver_server = ModbusUnitServer(
        SimUnit("receiver", SimClock(real_time=True)), "127.0.0.1", free_port
    )
    receiver_server.start()
    stream = tmp_path / "stream.csv"
    stream.write_text(
        "time_s,linear_um,straightness_v_um,straightness_w_um,angle_u_urad,"
        "angle_v_urad,angle_w_urad,beam_ok\n0,0,1,2,3,4,5,1\n"
    )
    path = tmp_path / "units.yaml"
    path.write_text(
        textwrap.dedent(f"""\
        format: xmalign.units/1
        launch: {{transport: modbus-tcp, host: 127.0.0.1, port: {receiver_server.port}}}
        receiver: {{transport: modbus-tcp, host: 127.0.0.1, port: {launch_server.port}}}
        interferometer: {{replay: stream.csv}}
        """)
    )
    config = load_units_config(path)
    try:
        with pytest.raises(XmalignError, match="is a receiver unit, expected a launch unit"):
            open_devices(config, reference_machine)
        config = config.model_copy(update={"launch": config.receiver, "receiver": config.launch})
        devices = open_devices(config, reference_machine, Operator([]).ask, Operator([]).tell)
        try:
            assert isinstance(devices.launch, ModbusUnit) and devices.receiver.kind == "receiver"
            assert devices.interferometer.read().channel("angle_w_urad") == 5.0
            with units_locked_on_exit(devices.launch, devices.receiver):
                devices.launch.move_to([0.001, 0.002], timeout_s=5.0)
                devices.receiver.move_to([0.001, 0.002, 0.003], timeout_s=5.0)
        finally:
            devices.close()
    finally:
        receiver_server.stop()


@pytest.mark.parametrize(
    ("content", "error", "fragment"),
    [
        (None, TransportError, "cannot read the machine position file"),
        (b"\xff\xfe 1 2 3\n", FormatError, "not UTF-8 text (byte 0)"),
        (b"# only a comment\n\n", FormatError, "no position in the file"),
    ],
)
def test_file_positions_refuse_a_missing_binary_or_empty_file(
    tmp_path: Path, content: bytes | None, error: type[Exception], fragment: str
) -> None:
    path = tmp_path / "pos.txt"
    if content is not None:
        path.write_bytes(content)
    source = FilePositions(path)
    assert source.is_standstill()
    with pytest.raises(error, match=re.escape(fragment)):
        source.position_mm()


class StuckCnc:
    """A mover that never stops, or stops ``miss_mm`` beside the target in X."""

    def __init__(self, *, stops: bool, miss_mm: float = 0.0) -> None:
        self.stops, self.miss_mm = stops, miss_mm
        self.at_mm = np.zeros(3)

    def position_mm(self) -> np.ndarray:
        return self.at_mm

    def is_standstill(self) -> bool:
        return self.stops

    def move_to(self, position_mm: np.ndarray, feed_mm_min: float) -> None:
        self.at_mm = np.asarray(position_mm, dtype=float) + [self.miss_mm, 0.0, 0.0]


def test_checked_mover_times_out_and_notices_a_missed_target(reference_machine) -> None:  # noqa: ANN001
    clock = SimClock()
    never = CheckedMover(StuckCnc(stops=False), reference_machine, clock=clock)
    assert not never.is_standstill()
    with pytest.raises(DeviceTimeoutError, match="the CNC did not come to a standstill"):
        never.move_to([100.0, 200.0, -50.0], 1000.0)
    assert clock.now() == pytest.approx(10.0, abs=0.1)
    beside = CheckedMover(StuckCnc(stops=True, miss_mm=0.2), reference_machine, clock=clock)
    with pytest.raises(OutOfRangeError, match="stopped 0.200 mm from"):
        beside.move_to([100.0, 200.0, -50.0], 1000.0)


def test_operator_prompt_stands_still_and_reports_the_confirmed_position(reference_machine) -> None:  # noqa: ANN001
    operator = Operator([""])
    mover = OperatorPrompt(reference_machine, operator.ask, operator.tell)
    assert mover.is_standstill()
    with pytest.raises(XmalignError, match="no answer from the operator"):
        mover.position_mm()  # asked where the machine stands before any move


def test_linuxcncrsh_source_with_defaults_and_its_program_path(tmp_path) -> None:  # noqa: ANN001
    path = tmp_path / "units.yaml"
    path.write_text(
        "format: xmalign.units/1\nlaunch: {transport: modbus-tcp, host: a}\n"
        "receiver: {transport: modbus-tcp, host: b}\ninterferometer: {port: /dev/null}\n"
        "machine_position:\n  source: linuxcncrsh\n"
        "  linuxcncrsh: {host: cnc, program: shared/run.ngc}\n"
    )
    rsh = load_units_config(path).machine_position.linuxcncrsh
    assert rsh is not None
    assert (rsh.port, *rsh.passwords()) == (5007, "EMC", "EMCTOO")
    assert (rsh.timeout_s, rsh.start_timeout_s) == (None, 5.0)  # timeouts.io_s; as before
    assert rsh.cnc_program_path == str((tmp_path / "shared" / "run.ngc").resolve())
    assert load_units_config(path).timeouts.machine_s == 600.0
    assert rsh.allow_mdi_moves is False  # xmalign moves no axis unless told to


@pytest.mark.parametrize(
    ("position", "fragment"),
    [
        ("{source: linuxcncrsh}", "'linuxcncrsh' is required with source: linuxcncrsh"),
        ("{source: linuxcncrsh, linuxcncrsh: {program: p.ngc}}", "linuxcncrsh.host"),
        (
            "{source: linuxcncrsh, linuxcncrsh: {host: h, program: p, tolerance_mm: 0}}",
            "linuxcncrsh.tolerance_mm",
        ),
        ("{source: prompt, linuxcncrsh: {host: h, program: p}}", "and only then"),
        (
            "{source: linuxcncrsh, linuxcncrsh: {host: h, program: p, allow_mdi_moves: maybe}}",
            "linuxcncrsh.allow_mdi_moves",
        ),
    ],
)
def test_bad_linuxcncrsh_source_names_the_key(tmp_path, position: str, fragment: str) -> None:  # noqa: ANN001
    path = tmp_path / "units.yaml"
    path.write_text(
        "format: xmalign.units/1\nlaunch: {transport: modbus-tcp, host: a}\n"
        "receiver: {transport: modbus-tcp, host: b}\ninterferometer: {port: /dev/null}\n"
        f"machine_position: {position}\n"
    )
    with pytest.raises(InputError, match=f"units.yaml: .*{fragment}"):
        load_units_config(path)
