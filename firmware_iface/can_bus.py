"""Opening a CAN bus, and ``udp_local``: the simulated CAN bus between processes.

``udp_local`` carries python-can's ``udp_multicast`` frames (msgpack, UDP port
43113, an IPv4 multicast group as the channel) but, unlike python-can's
``udp_multicast`` bus, it

* stays on one network interface: the loopback (127.0.0.1) unless ``host``
  names the address of another interface of this computer. Its receiving
  socket is bound to the group address, so no unicast datagram reaches it,
  and it joins the group on that interface only (IP_MULTICAST_ALL off), so
  no IGMP report leaves by another interface and no frame from one is heard;
* sends with a time-to-live of ``hop_limit`` (0: the frames never leave the
  computer);
* does not hand a bus its own frames back, as a CAN controller does not
  (python-can's bus does, and canopen then takes an RPDO it sent for one the
  node transmits periodically, and stops sending it).

:func:`open_can_bus` opens it or any python-can interface, with one clear
error for a bad interface name or channel. Every frame is logged by canopen
and the drivers, not here.
"""

from __future__ import annotations

import ipaddress
import logging
import select
import socket
import sys
import time
from typing import Any

import can
from can.interfaces.udp_multicast.utils import pack_message, unpack_message

from xmalign.errors import TransportError

log = logging.getLogger(__name__)

#: The interface name of :class:`LocalUdpBus` for :func:`open_can_bus` and python-can.
UDP_LOCAL = "udp_local"
DEFAULT_PORT = 43113
LOOPBACK = "127.0.0.1"
#: Linux: deliver only the groups this socket joined (not every group joined on the host).
_IP_MULTICAST_ALL = getattr(socket, "IP_MULTICAST_ALL", 49)
_MAX_DATAGRAM = 4096


def multicast_group(channel: str) -> str:
    """The IPv4 multicast group of a ``udp_local`` channel; ValueError (one line) if it is none."""
    try:
        address = ipaddress.IPv4Address(channel)
    except ValueError:
        address = None
    if address is None or not address.is_multicast:
        raise ValueError(
            f"{channel!r} is not an IPv4 multicast group (224.0.0.0 to 239.255.255.255;"
            " 239.x.x.x for a bus of one's own, e.g. 239.74.163.2)"
        )
    return str(address)


def check_interface(interface: str) -> None:
    """ValueError (one line, naming the choices) unless ``interface`` is a CAN interface we know."""
    if interface != UDP_LOCAL and interface not in can.VALID_INTERFACES:
        raise ValueError(
            f"no CAN interface {interface!r}: {UDP_LOCAL} (the simulated bus) or one of"
            f" python-can's ({', '.join(sorted(can.VALID_INTERFACES))})"
        )


class LocalUdpBus(can.BusABC):
    """The ``udp_local`` bus (module docstring): one interface, TTL ``hop_limit``, no echo.

    Parameters
    ----------
    channel : str
        IPv4 multicast group, e.g. ``"239.74.163.2"``.
    port : int
        UDP port of the group (python-can's ``udp_multicast`` default, 43113).
    host : str
        IPv4 address of the interface the bus runs on (default the loopback).
    hop_limit : int
        Time-to-live of the frames sent; 0 keeps them on this computer.
    """

    def __init__(
        self,
        channel: str,
        port: int = DEFAULT_PORT,
        host: str = LOOPBACK,
        hop_limit: int = 0,
        **kwargs: Any,
    ) -> None:
        try:
            group = multicast_group(channel)
        except ValueError as error:
            raise can.CanInitializationError(str(error)) from error
        kwargs.pop("bitrate", None)  # a simulated bus has none
        self._receiver = _receiving_socket(group, port, host)
        try:
            self._sender = _sending_socket(host, hop_limit)
            super().__init__(channel, **kwargs)
        except BaseException:
            self._receiver.close()
            raise
        self.channel_info = f"{UDP_LOCAL} {group}:{port} on {host} (TTL {hop_limit})"
        self._destination = (group, port)
        self._own_address = self._sender.getsockname()

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            try:
                ready, _, _ = select.select([self._receiver], [], [], remaining)
                if not ready:
                    return None, False
                data, sender = self._receiver.recvfrom(_MAX_DATAGRAM)
            except OSError as error:
                raise can.CanOperationError(f"{self.channel_info}: {error}") from error
            if sender[:2] == self._own_address[:2]:
                continue  # our own frame: a CAN controller does not receive what it sends
            try:
                message = unpack_message(data, replace={"timestamp": time.time()}, check=True)
            except Exception as error:  # msgpack raises several types for a foreign datagram
                log.warning("%s: dropped a datagram from %s: %s", self.channel_info, sender, error)
                continue  # one stray datagram must not end the bus's reader
            return message, False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        try:
            self._sender.sendto(pack_message(msg), self._destination)
        except OSError as error:
            raise can.CanOperationError(f"{self.channel_info}: {error}") from error

    def fileno(self) -> int:
        return self._receiver.fileno()

    def shutdown(self) -> None:
        super().shutdown()
        self._sender.close()
        self._receiver.close()


def _receiving_socket(group: str, port: int, host: str) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if hasattr(socket, "SO_REUSEPORT"):  # several buses (processes) on one group and port
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        sock.bind((group, port))  # the group's datagrams only, never a unicast one
        membership = socket.inet_aton(group) + socket.inet_aton(host)
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, membership)
        if sys.platform.startswith("linux"):
            sock.setsockopt(socket.IPPROTO_IP, _IP_MULTICAST_ALL, 0)
    except OSError as error:
        sock.close()
        raise can.CanInitializationError(
            f"cannot join the multicast group {group} on {host}: {error.strerror or error}"
        ) from error
    return sock


def _sending_socket(host: str, hop_limit: int) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.bind((host, 0))  # its own address and port: how the bus knows its echo
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(host))
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, hop_limit)
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)  # other local processes
    except OSError as error:
        sock.close()
        raise can.CanInitializationError(
            f"cannot send from {host}: {error.strerror or error}"
        ) from error
    return sock


def open_can_bus(
    interface: str,
    channel: str,
    *,
    bitrate: int | None = None,
    host: str = LOOPBACK,
    hop_limit: int = 0,
) -> can.BusABC:
    """A CAN bus: ``udp_local`` (:class:`LocalUdpBus`) or any python-can interface.

    ``host`` is for ``udp_local`` only; ``hop_limit`` for ``udp_local`` and python-can's
    ``udp_multicast`` (its TTL). Raises TransportError with one line that names the
    interface and the channel.
    """
    try:
        check_interface(interface)
        if interface == UDP_LOCAL:
            return LocalUdpBus(channel, host=_ipv4_of(host), hop_limit=hop_limit)
        options: dict[str, Any] = {} if bitrate is None else {"bitrate": bitrate}
        if interface == "udp_multicast":
            options["hop_limit"] = hop_limit
        return can.Bus(interface=interface, channel=channel, **options)
    except (can.CanError, OSError, ValueError, ImportError) as error:
        raise TransportError(f"cannot open the CAN bus {channel} ({interface}): {error}") from error


def _ipv4_of(host: str) -> str:
    try:
        return socket.gethostbyname(host)
    except OSError as error:
        raise can.CanInitializationError(
            f"host {host!r} is not an IPv4 address of this computer"
        ) from error
