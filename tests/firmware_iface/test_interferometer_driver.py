"""Interferometer drivers: the line protocol over a simulator pty, and replay of a stream."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
import serial

from firmware_iface.interferometer import (
    STREAM_HEADER,
    RecordingInterferometer,
    ReplayInterferometer,
    SerialInterferometer,
    open_serial,
)
from firmware_iface.xm_line_protocol import Reply, encode_reply, encode_sample
from sim.servers.serial_pty import IDENTIFICATION, PtyInterferometerServer
from sim.world import build_world
from xmalign.errors import (
    DeviceError,
    DeviceTimeoutError,
    FormatError,
    TransportError,
)
from xmalign.roles import InterferometerReading


@pytest.fixture
def served(reference_machine) -> Iterator[tuple[object, SerialInterferometer]]:  # noqa: ANN001
    world = build_world(reference_machine, seed=4, real_time=True)
    server = PtyInterferometerServer(world.interferometer, rate_hz=200.0)
    server.start()
    connection = open_serial(server.port, timeout_s=1.0)
    yield world, SerialInterferometer(connection, f"interferometer on {server.port}")
    connection.close()
    server.stop()


def test_identify_read_zero_and_average_over_the_pty(served) -> None:  # noqa: ANN001
    world, interferometer = served
    assert interferometer.identify() == IDENTIFICATION
    reading = interferometer.read()
    assert reading.channels.shape == (6,)
    assert reading.beam_ok == world.interferometer.geometry().beam_ok
    interferometer.zero()
    assert abs(interferometer.read().channel("linear_um")) < 1.0
    interferometer.set_rate(100)
    mean = interferometer.average(0.1)
    expected = world.interferometer.geometry().channels[1:]
    np.testing.assert_allclose(mean.channels[1:], expected, atol=1.0)


def test_refused_command_is_a_device_error(served) -> None:  # noqa: ANN001
    _, interferometer = served
    with pytest.raises(DeviceError, match="refused RATE: RATE 5000 outside 1 to 1000"):
        interferometer.set_rate(5000)


class ScriptedLine:
    """A serial connection that answers with prepared lines (b'' = read timeout)."""

    def __init__(self, lines: list[bytes]) -> None:
        self.lines = lines
        self.written: list[bytes] = []

    def write(self, data: bytes) -> int:
        self.written.append(data)
        return len(data)

    def readline(self) -> bytes:
        return self.lines.pop(0) if self.lines else b""

    def reset_input_buffer(self) -> None:
        pass


SAMPLE = InterferometerReading(1.5, np.array([1.0, 2.0, -3.0, 4.0, 5.0, -6.0]), True)


def test_corrupted_lines_are_discarded_and_counted() -> None:
    good = encode_sample(SAMPLE)
    broken = good.replace(b"2.0000", b"2.0001")  # checksum no longer matches
    line = ScriptedLine([encode_reply(Reply(True, "READ")), broken, b"garbage\n", good])
    interferometer = SerialInterferometer(line)
    reading = interferometer.read()
    np.testing.assert_allclose(reading.channels, SAMPLE.channels)
    assert interferometer.corrupted_lines == 2
    assert line.written == [b"READ\n"]


def test_a_line_that_stays_corrupted_is_a_transport_error() -> None:
    line = ScriptedLine([b"noise*00\n"] * 10)
    with pytest.raises(TransportError, match="line from the interferometer is corrupted"):
        SerialInterferometer(line).read()


def test_silence_is_a_timeout_naming_the_instrument() -> None:
    with pytest.raises(DeviceTimeoutError, match="interferometer on /dev/ttyX did not answer"):
        SerialInterferometer(ScriptedLine([]), "interferometer on /dev/ttyX").zero()


def test_recorded_stream_replays_the_same_readings(reference_machine, tmp_path) -> None:  # noqa: ANN001
    world = build_world(reference_machine, seed=5)
    path = tmp_path / "stream.csv"
    recorder = RecordingInterferometer(world.interferometer, path)
    recorded = [recorder.read(), recorder.average(0.1), recorder.read()]
    recorder.close()
    replay = ReplayInterferometer(path)
    replayed = [replay.read(), replay.read(), replay.read()]
    for a, b in zip(recorded, replayed, strict=True):
        assert b.time_s == pytest.approx(a.time_s, abs=1e-6)
        np.testing.assert_allclose(b.channels, a.channels, atol=1e-4)
        assert b.beam_ok == a.beam_ok
    with pytest.raises(DeviceError, match="stream.csv has no more samples"):
        replay.read()


def test_replay_average_and_zero(tmp_path) -> None:  # noqa: ANN001
    path = tmp_path / "s.csv"
    rows = [f"{0.02 * i:.6f},{10.0 + i:.4f},1,2,3,4,5,{int(i != 3)}" for i in range(6)]
    path.write_text(
        "time_s,linear_um,straightness_v_um,straightness_w_um,angle_u_urad,"
        "angle_v_urad,angle_w_urad,beam_ok\n" + "\n".join(rows) + "\n"
    )
    replay = ReplayInterferometer(path)
    replay.zero()
    mean = replay.average(0.05)  # samples at 0, 0.02, 0.04, 0.06 s
    assert mean.channel("linear_um") == pytest.approx(1.5)
    assert not mean.beam_ok  # the fourth sample had lost the beam
    assert replay.remaining == 2


def test_bad_stream_file_names_the_line(tmp_path) -> None:  # noqa: ANN001
    path = tmp_path / "bad.csv"
    path.write_text(
        "time_s,linear_um,straightness_v_um,straightness_w_um,angle_u_urad,"
        "angle_v_urad,angle_w_urad,beam_ok\n0,1,2,3,4,5,6,1\n0.02,1,2,x,4,5,6,1\n"
    )
    with pytest.raises(FormatError, match="bad.csv: line 3"):
        ReplayInterferometer(path)


class UnpluggedLine(ScriptedLine):
    """A serial connection whose cable was pulled: writes or reads fail as pyserial's do."""

    def __init__(self, *, fails_on: str) -> None:
        super().__init__([])
        self.fails_on = fails_on

    def write(self, data: bytes) -> int:
        if self.fails_on == "write":
            raise serial.SerialException("write failed: [Errno 5] Input/output error")
        return super().write(data)

    def readline(self) -> bytes:
        if self.fails_on == "read":
            raise OSError(5, "Input/output error")
        return super().readline()


@pytest.mark.parametrize("fails_on", ["write", "read"])
def test_a_pulled_cable_is_a_transport_error(fails_on: str) -> None:
    line = UnpluggedLine(fails_on=fails_on)
    with pytest.raises(TransportError, match="lost the connection to the interferometer on /dev/"):
        SerialInterferometer(line, "interferometer on /dev/ttyUSB0").zero()


def test_samples_before_the_reply_are_skipped() -> None:
    line = ScriptedLine([encode_sample(SAMPLE), encode_reply(Reply(True, "ZERO"))])
    SerialInterferometer(line).zero()
    assert line.written == [b"ZERO\n"] and not line.lines


def test_a_missing_port_is_named(tmp_path) -> None:  # noqa: ANN001
    with pytest.raises(TransportError, match="cannot open the interferometer port .*ttyNONE"):
        open_serial(str(tmp_path / "ttyNONE"))


def test_the_recorder_zeroes_the_instrument_it_reads(reference_machine, tmp_path) -> None:  # noqa: ANN001
    world = build_world(reference_machine, seed=5)
    recorder = RecordingInterferometer(world.interferometer, tmp_path / "stream.csv")
    recorder.zero()
    assert np.allclose(recorder.read().channels[0], 0.0, atol=1.0)  # linear um from the zero
    recorder.close()


HEADER = ",".join(STREAM_HEADER) + "\n"


@pytest.mark.parametrize(
    ("body", "fragment"),
    [
        ("", "no samples"),
        (None, "line 1: expected the header time_s,linear_um"),
        ("\n0,1,2,3,4,5,6,1\n0.02,1,2,3\n", "line 4: expected 8 fields"),
        ("0,1,2,3,4,5,6,1\n0.02,1,2,nan,4,5,6,1\n", "line 3: a value is not a finite number"),
    ],
)
def test_stream_files_without_samples_or_with_bad_rows(
    tmp_path, body: str | None, fragment: str
) -> None:  # noqa: ANN001
    path = tmp_path / "s.csv"
    path.write_text(HEADER + body if body is not None else "t,x\n0,1\n")
    with pytest.raises(FormatError, match=f"s.csv: {fragment}"):
        ReplayInterferometer(path)
