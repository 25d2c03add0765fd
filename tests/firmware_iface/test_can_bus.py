"""The udp_local bus (the simulated CAN bus between processes) and opening a CAN bus."""

from __future__ import annotations

import importlib
import socket
import tomllib
import uuid
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from firmware_iface.can_bus import DEFAULT_PORT, UDP_LOCAL, LocalUdpBus, open_can_bus
from xmalign.errors import TransportError

ROOT = Path(__file__).resolve().parents[2]


def frame(can_id: int, data: bytes) -> can.Message:
    return can.Message(arbitration_id=can_id, data=data, is_extended_id=False)


@pytest.fixture
def group() -> str:
    return "239.74.{}.{}".format(*uuid.uuid4().bytes[:2])  # a bus of its own per test


@pytest.fixture
def two(group: str) -> Iterator[tuple[LocalUdpBus, LocalUdpBus]]:
    first, second = LocalUdpBus(group), LocalUdpBus(group)
    yield first, second
    first.shutdown()
    second.shutdown()


def test_a_frame_reaches_the_others_but_not_its_sender(two) -> None:  # noqa: ANN001
    first, second = two
    first.send(frame(0x601, b"\x40\x00\x10\x00"))
    received = second.recv(1.0)
    assert received is not None
    assert (received.arbitration_id, bytes(received.data)) == (0x601, b"\x40\x00\x10\x00")
    assert first.recv(0.3) is None  # no echo, as on a CAN controller
    second.send(frame(0x581, b"\x43"))
    assert first.recv(1.0).arbitration_id == 0x581


def test_another_group_is_another_bus(two) -> None:  # noqa: ANN001
    first, _ = two
    other = LocalUdpBus("239.74.{}.{}".format(*uuid.uuid4().bytes[:2]))
    try:
        first.send(frame(0x77F, b"\x05"))
        assert other.recv(0.3) is None
    finally:
        other.shutdown()


def test_a_stray_datagram_is_dropped_and_the_bus_goes_on(two, group: str) -> None:  # noqa: ANN001
    first, second = two
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as stray:
        stray.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
        stray.sendto(b"not a frame", (group, DEFAULT_PORT))
    first.send(frame(0x77F, b"\x05"))
    received = second.recv(1.0)
    assert received is not None and received.arbitration_id == 0x77F


def test_it_stays_on_the_loopback_with_ttl_0(two, group: str) -> None:  # noqa: ANN001
    first, _ = two
    assert first._receiver.getsockname() == (group, DEFAULT_PORT)  # no unicast reaches it
    sender = first._sender
    assert sender.getsockname()[0] == "127.0.0.1"
    assert sender.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL) == 0
    interface = sender.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, 4)
    assert socket.inet_ntoa(interface) == "127.0.0.1"
    assert first.channel_info == f"udp_local {group}:{DEFAULT_PORT} on 127.0.0.1 (TTL 0)"


def test_a_unicast_datagram_does_not_reach_it(two) -> None:  # noqa: ANN001
    from can.interfaces.udp_multicast.utils import pack_message

    first, _ = two
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
        sender.sendto(pack_message(frame(0x601, b"\x40")), ("127.0.0.1", DEFAULT_PORT))
    assert first.recv(0.3) is None


def test_python_can_tools_can_listen_in(group: str) -> None:
    """python-can's own udp_multicast bus (its can.logger, can.viewer) hears the frames."""
    listener = can.Bus(interface="udp_multicast", channel=group, hop_limit=0)
    local = LocalUdpBus(group)
    try:
        local.send(frame(0x181, b"\x37\x02"))
        heard = listener.recv(1.0)
        assert heard is not None and heard.arbitration_id == 0x181
    finally:
        listener.shutdown()
        local.shutdown()


def test_hop_limit_sets_the_ttl(group: str) -> None:
    bus = open_can_bus(UDP_LOCAL, group, hop_limit=1)
    try:
        assert bus._sender.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL) == 1  # type: ignore[attr-defined]
    finally:
        bus.shutdown()


@pytest.mark.parametrize(
    ("interface", "channel", "host", "message"),
    [
        ("nosuchbus", "x", "127.0.0.1", "no CAN interface 'nosuchbus': udp_local (the simulated"),
        (UDP_LOCAL, "999.999.1.1", "127.0.0.1", "'999.999.1.1' is not an IPv4 multicast group"),
        (UDP_LOCAL, "10.0.0.1", "127.0.0.1", "'10.0.0.1' is not an IPv4 multicast group"),
        (UDP_LOCAL, "239.74.1.1", "nosuchhost.invalid", "'nosuchhost.invalid' is not an IPv4"),
        (UDP_LOCAL, "239.74.1.1", "192.0.2.254", "cannot join the multicast group 239.74.1.1"),
    ],
)
def test_a_bus_that_cannot_be_opened_is_one_line(interface, channel, host, message) -> None:  # noqa: ANN001
    with pytest.raises(TransportError) as error:
        open_can_bus(interface, channel, host=host)
    assert message in str(error.value) and "\n" not in str(error.value)


def test_python_can_finds_it_by_name_once_installed() -> None:
    """pyproject declares the bus as python-can interface udp_local (an entry point)."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    module, _, name = project["project"]["entry-points"]["can.interface"][UDP_LOCAL].partition(":")
    assert getattr(importlib.import_module(module), name) is LocalUdpBus
