"""A SINUMERIK 840D sl / ONE followed through its OPC UA server (``asyncua``; docs/hardware.md).

Two layers, as for every device:

* :class:`OpcUaLink` holds one OPC UA session (``asyncua``'s synchronous
  client): read node values, browse, call a method, each with a timeout;
  every read and call is logged at DEBUG with its node ids and values. The
  password is never logged or put in a message.
* :class:`SinumerikMachine` reads the NC variables the SINUMERIK OPC UA server
  publishes under namespace 2 with string identifiers (SINUMERIK OPC UA
  configuration manual, "Variable paths for NC access"; the variables are those
  of the NC variable list manual, indexed ``[u<unit>,<index>]``):

  ==============================================  ==========================================
  ``/Channel/MachineAxis/actToolBasePos[u1,i]``   actual position of machine axis ``i`` of
                                                  channel 1 in machine coordinates (MCS)
  ``/Channel/State/progStatus[u1]``               program state: 1 interrupted, 2 stopped,
                                                  3 in progress, 4 waiting, 5 aborted
  ``/Channel/State/chanStatus[u1]``               channel state: 0 reset, 1 active,
                                                  2 interrupted
  ``/Channel/ProgramInfo/selectedWorkPProg[u1]``  the selected program
  ``/Bag/State/opMode[u1]``                       mode group's mode: 0 JOG, 1 MDA, 2 AUTO
  ==============================================  ==========================================

  and selects a program with the server's ``Select`` method (configuration
  manual 05/2022, 7.6 "Select": ``Select(SourceFileNodeId: String,
  ChannelNumber: Int32) -> StatusCode: Int32``, 0 good, 1 channel not found, 2
  program not found, 3 channel not in reset, 4 refused; the ``ApWrite`` right;
  the program named by its path in the server's file system,
  ``Sinumerik/FileSystem/Part Program/<name>.mpf``). It copies a program to the
  NC with ``CopyFileToServer`` (7.5 "File system": ``CopyFileToServer(
  TargetFilename: String, Data: ByteString, Overwrite: Boolean)``, the
  ``FsWrite`` right, files up to 16 MB, one extension). The methods' nodes are
  found by their browse names under ``/Methods`` (``/Methods/Select`` or
  ``/Methods/Filehandling/Select``, depending on the server's version).

  ``measPos1`` (``/Channel/MachineAxis/measPos1``) is the position a probe
  latched, not the actual position: it is not used. The manual documents no
  method that starts, holds or resumes a program (NC start is a PLC interface
  signal): xmalign does not start a program on a SINUMERIK; the operator
  presses cycle start and the run follows the machine.

Standstill: the positions read on successive calls stayed within
``standstill_tolerance_mm`` for ``settle_s`` (:class:`StandstillWindow`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from asyncua import ua
from asyncua.sync import Client, ThreadLoop, ThreadLoopNotRunning
from asyncua.ua.attribute_ids import AttributeIds
from asyncua.ua.status_codes import StatusCodes
from asyncua.ua.uaerrors import UaError, UaStatusCodeError

from firmware_iface.controller_status import ControllerStatus
from firmware_iface.standstill import StandstillWindow
from xmalign.errors import DeviceError, DeviceTimeoutError, TransportError, XmalignError
from xmalign.geometry import Vec
from xmalign.program_check import same_program
from xmalign.roles import Clock, ClosesOnExit, ProgramReport, ProgramState, WallClock

log = logging.getLogger(__name__)

#: The namespace index of the SINUMERIK NC variables (the manual's ``ns=2``).
NAMESPACE = 2
MM_PER_UNIT = {"mm": 1.0, "inch": 25.4}
#: progStatus values (NC variable list manual) and what they mean for a run.
PROG_STATUS: dict[int, tuple[str, ProgramState]] = {
    1: ("interrupted", "paused"),
    2: ("stopped", "paused"),
    3: ("in progress", "running"),
    4: ("waiting", "running"),
    5: ("aborted", "idle"),
}
CHAN_STATUS = {0: "reset", 1: "active", 2: "interrupted"}
OP_MODE = {0: "JOG", 1: "MDA", 2: "AUTOMATIC"}
SELECT_STATUS = {
    1: "channel not found",
    2: "program not found",
    3: "channel not in reset",
    4: "refused by the NC",
}
#: Status codes that mean the session or connection is gone (a transport failure).
_LOST = {
    StatusCodes.BadConnectionClosed,
    StatusCodes.BadSessionClosed,
    StatusCodes.BadSessionIdInvalid,
    StatusCodes.BadSecureChannelClosed,
    StatusCodes.BadServerNotConnected,
    StatusCodes.BadCommunicationError,
    StatusCodes.BadTimeout,
}


@dataclass(frozen=True)
class OpcUaSecurity:
    """Secure channel and identity of an OPC UA session.

    ``policy`` ``None`` sends nothing encrypted (a user's password in plain
    text: only on a network of its own). Otherwise ``certificate`` (DER or PEM)
    and ``private_key`` (PEM) are the client's, trusted by the server;
    ``server_certificate`` pins the server's. ``identity`` is ``user`` (user and
    password), ``certificate`` (the client certificate as user identity) or
    ``anonymous``.
    """

    policy: str = "None"
    mode: Literal["Sign", "SignAndEncrypt"] = "SignAndEncrypt"
    certificate: Path | None = None
    private_key: Path | None = None
    server_certificate: Path | None = None
    identity: Literal["user", "certificate", "anonymous"] = "anonymous"
    user: str | None = None
    password: str | None = None

    def __repr__(self) -> str:  # never show the password, not even in a traceback
        return (
            f"OpcUaSecurity(policy={self.policy!r}, identity={self.identity!r}, user={self.user!r})"
        )


class _Masked(logging.Filter):
    """Replaces a secret in every record of a logger (asyncua dumps requests at DEBUG)."""

    def __init__(self, secret: str) -> None:
        super().__init__()
        self.secret = secret

    def filter(self, record: logging.LogRecord) -> bool:
        text = record.getMessage()
        if self.secret in text:
            record.msg, record.args = text.replace(self.secret, "****"), ()
        return True


def _client_loggers() -> list[logging.Logger]:
    """asyncua's client loggers (a filter acts only on records of its own logger)."""
    names = {
        "asyncua.client.client",
        "asyncua.client.ua_client.UaClient",
        "asyncua.client.ua_client.UASocketProtocol",
        *(n for n in logging.root.manager.loggerDict if n.startswith("asyncua.client")),
    }
    return [logging.getLogger(name) for name in sorted(names)]


class OpcUaLink:
    """One OPC UA session with a server: read, browse, call.

    Parameters
    ----------
    endpoint : str
        ``opc.tcp://host:port`` (the SINUMERIK default port is 4840).
    timeout_s : float
        Largest wait for the connection and for each request.
    security : OpcUaSecurity
    """

    def __init__(self, endpoint: str, timeout_s: float, security: OpcUaSecurity) -> None:
        self.endpoint = endpoint
        self.timeout_s = timeout_s
        self.security = security
        self.name = f"the SINUMERIK OPC UA server at {endpoint}"
        self._client: Client | None = None
        self._mask = _Masked(security.password) if security.password else None

    def open(self) -> None:
        """Connect, with the security and the identity of the configuration."""
        # asyncua times each request out itself; the wrapper's own limit is a backstop
        backstop_s = 4 * self.timeout_s + 5
        # a daemon thread: a session left open by a crash never keeps xmalign from exiting
        thread = ThreadLoop(backstop_s)
        thread.daemon = True
        thread.start()
        client = Client(self.endpoint, timeout=self.timeout_s, tloop=thread)
        self._masking(True)
        try:
            self._configure(client)
            who = f" as {self.security.user!r}" if self.security.identity == "user" else ""
            log.debug("%s > connect%s (%s)", self.name, who, self.security.policy)
            client.connect()
        except BaseException as error:
            _stop(client)
            self._masking(False)
            if not isinstance(error, Exception):
                raise
            raise self._error("cannot open a session with", error) from error
        self._client = client

    def _masking(self, on: bool) -> None:
        """While a session lives, asyncua's loggers never show the password."""
        if self._mask is None:
            return
        for logger in _client_loggers():
            (logger.addFilter if on else logger.removeFilter)(self._mask)

    def _configure(self, client: Client) -> None:
        security = self.security
        if security.policy != "None":
            parts = [security.policy, security.mode, str(security.certificate)]
            parts += [str(security.private_key)]
            if security.server_certificate is not None:
                parts.append(str(security.server_certificate))
            client.set_security_string(",".join(parts))
        if security.identity == "user":
            client.set_user(security.user or "")
            client.set_password(security.password or "")
        elif security.identity == "certificate":
            client.load_client_certificate(str(security.certificate))
            client.load_private_key(str(security.private_key))

    def _error(self, doing: str, error: Exception) -> XmalignError:
        """The project's error for what asyncua raised (one line naming the server)."""
        if isinstance(error, UaStatusCodeError):
            text = f"{doing} {self.name}: {ua.StatusCode(error.code).name}"
            if error.code == StatusCodes.BadTimeout:
                return DeviceTimeoutError(text)
            return TransportError(text) if error.code in _LOST else DeviceError(text)
        if isinstance(error, TimeoutError):
            return DeviceTimeoutError(f"{self.name} did not answer within {self.timeout_s:g} s")
        if isinstance(error, OSError):
            return TransportError(f"{doing} {self.name} ({error.strerror or error})")
        if isinstance(error, UaError | ThreadLoopNotRunning):
            return TransportError(f"{doing} {self.name} ({error})")
        return TransportError(f"{doing} {self.name} ({type(error).__name__}: {error})")

    @property
    def is_open(self) -> bool:
        """Whether a session is open."""
        return self._client is not None

    @property
    def client(self) -> Client:
        """The open session's asyncua client; TransportError once closed."""
        if self._client is None:
            raise TransportError(f"no session with {self.name} (closed)")
        return self._client

    def read(self, node_ids: Sequence[str]) -> list[Any]:
        """Values of ``ns=2;s=<id>`` nodes; DeviceError names a node the server refused."""
        nodes = [self.client.get_node(_node(i)) for i in node_ids]
        log.debug("%s > read %s", self.name, ", ".join(node_ids))
        try:
            values = self.client.read_attributes(nodes, AttributeIds.Value)
        except Exception as error:
            raise self._error("lost the session with", error) from error
        for node_id, value in zip(node_ids, values, strict=True):
            if value.StatusCode is not None and not value.StatusCode.is_good():
                name = value.StatusCode.name
                raise DeviceError(f"{self.name} refused to read ns=2;s={node_id} ({name})")
        result = [None if v.Value is None else v.Value.Value for v in values]
        log.debug("%s < %s", self.name, result)
        return result

    def find_method(self, folder_id: str, browse_name: str) -> tuple[str, str]:
        """``(object id, method id)`` of the method named ``browse_name`` under ``folder_id``.

        Searches the folder and its child objects (two levels, as the server
        versions differ in where they put the methods).
        """
        folders = [self.client.get_node(_node(folder_id))]
        try:
            for _level in range(2):
                children = []
                for folder in folders:
                    for child in folder.get_children():
                        if child.read_browse_name().Name == browse_name:
                            return str(folder.nodeid.Identifier), str(child.nodeid.Identifier)
                        children.append(child)
                folders = children
        except Exception as error:
            raise self._error(f"cannot browse {folder_id} of", error) from error
        raise DeviceError(f"{self.name} offers no method {browse_name} under {folder_id}")

    def call(self, object_id: str, method_id: str, *arguments: ua.Variant) -> list[Any]:
        """Call a method; its output arguments."""
        log.debug("%s > call %s%s", self.name, method_id, tuple(a.Value for a in arguments))
        node = self.client.get_node(_node(object_id))
        try:
            outputs = node.call_method(_node(method_id), *arguments)
        except Exception as error:
            raise self._error(f"{method_id} refused by", error) from error
        outputs = outputs if isinstance(outputs, list) else [outputs]
        log.debug("%s < %s", self.name, outputs)
        return outputs

    def close(self) -> None:
        """End the session (idempotent)."""
        client, self._client = self._client, None
        if client is not None:
            try:
                client.disconnect()
            except Exception as error:  # the session is gone either way
                log.debug("%s: disconnect failed (%s)", self.name, error)
            _stop(client)
            self._masking(False)


def _node(identifier: str) -> ua.NodeId:
    """The node ``ns=2;s=<identifier>``."""
    return ua.NodeId.from_string(f"ns={NAMESPACE};s={identifier}")


def _stop(client: Client) -> None:
    """End the client's event-loop thread (once)."""
    loop = client.tloop.loop
    if loop is not None and not loop.is_closed():
        client.tloop.stop()


class SinumerikMachine(ClosesOnExit):
    """The machine as its SINUMERIK OPC UA server reports it (``MachinePositionSource``).

    Parameters
    ----------
    link : OpcUaLink
    channel : int
        The NC channel that runs the program (``u<channel>`` in the variable paths).
    axis_indices : sequence of 3 int
        The machine axes of the channel giving x, y, z of the plan (1-based).
    length_unit : {"mm", "inch"}
        The NC's basic system for lengths (machine data 10240): positions in
        inch are converted to mm.
    clock, settle_s, standstill_tolerance_mm :
        Standstill: position unchanged within the tolerance for the settle time.
    mode_group : int
        The mode group of the channel (``/Bag/State/opMode[u<n>]``).
    """

    def __init__(
        self,
        link: OpcUaLink,
        channel: int = 1,
        axis_indices: Sequence[int] = (1, 2, 3),
        length_unit: Literal["mm", "inch"] = "mm",
        clock: Clock | None = None,
        settle_s: float = 0.2,
        standstill_tolerance_mm: float = 0.002,
        mode_group: int = 1,
    ) -> None:
        if len(axis_indices) != 3:
            raise ValueError("axis_indices: expected three machine axes (x, y, z)")
        self.link = link
        self.name = link.name
        self.channel = channel
        self._mm_per_unit = MM_PER_UNIT[length_unit]
        self._window = StandstillWindow(clock or WallClock(), settle_s, standstill_tolerance_mm)
        self.position_nodes = [
            f"/Channel/MachineAxis/actToolBasePos[u{channel},{i}]" for i in axis_indices
        ]
        self.prog_status_node = f"/Channel/State/progStatus[u{channel}]"
        self.chan_status_node = f"/Channel/State/chanStatus[u{channel}]"
        self.selected_node = f"/Channel/ProgramInfo/selectedWorkPProg[u{channel}]"
        self.mode_node = f"/Bag/State/opMode[u{mode_group}]"

    def open(self) -> SinumerikMachine:
        """Open the session and read the position once (every axis node is there)."""
        self.link.open()
        try:
            self.position_mm()  # every axis node is there, now rather than mid-run
        except BaseException:
            self.link.close()
            raise
        return self

    def close(self) -> None:
        """End the session."""
        self.link.close()

    def __enter__(self) -> SinumerikMachine:
        return self if self.link.is_open else self.open()

    # -- the role ----------------------------------------------------------------
    def position_mm(self) -> Vec:
        """Actual position in machine coordinates, shape (3,), mm."""
        return self._position(self.link.read(self.position_nodes))

    def is_standstill(self) -> bool:
        """The position stayed within the tolerance for the settle time."""
        return self._window.add(self.position_mm())

    def program_state(self) -> ProgramState:
        """``idle``, ``running`` or ``paused`` from the channel's ``progStatus``."""
        return self.status().program_state

    def status(self) -> ControllerStatus:
        """Position, program state and mode in one read."""
        nodes = [*self.position_nodes, self.prog_status_node, self.chan_status_node]
        values = self.link.read([*nodes, self.mode_node])
        position = self._position(values[:3])
        prog, chan, mode = (_integer(v) for v in values[3:])
        state = self._state(values[3])
        text = f"progStatus {prog} ({PROG_STATUS[prog][0]}), chanStatus {chan}"
        text += f" ({CHAN_STATUS.get(chan, '?')})"
        return ControllerStatus(position, state, text, OP_MODE.get(mode))

    def _state(self, prog_status: Any) -> ProgramState:
        prog = _integer(prog_status)
        if prog not in PROG_STATUS:
            raise DeviceError(f"{self.name} reports an unknown progStatus {prog_status!r}")
        return PROG_STATUS[prog][1]

    def loaded_program(self) -> str | None:
        """The selected program as the NC shows it, None if none."""
        value = self.link.read([self.selected_node])[0]
        return str(value) if value else None

    def program_report(self) -> ProgramReport:
        """The selected program (NC notation, ``/_N_MPF_DIR/_N_RUN_MPF``) and its state."""
        selected, prog = self.link.read([self.selected_node, self.prog_status_node])
        return ProgramReport(str(selected) if selected else None, self._state(prog))

    def select_program(self, path: str) -> None:
        """Select ``path`` (the server's file path) in the channel and check the NC shows it
        selected; DeviceError (with Select's status in words) otherwise."""
        folder, method = self.link.find_method("/Methods", "Select")
        outputs = self.link.call(
            folder,
            method,
            ua.Variant(path, ua.VariantType.String),
            ua.Variant(self.channel, ua.VariantType.Int32),
        )
        status = _integer(outputs[0]) if outputs else -1
        if status != 0:
            why = SELECT_STATUS.get(status, f"status {outputs[0] if outputs else None}")
            raise DeviceError(
                f"{self.name} did not select {path} in channel {self.channel}:"
                f" Select answered {status} ({why})"
            )
        selected = self.loaded_program()
        if selected is None or not same_program(selected, path):
            raise DeviceError(
                f"{self.name} accepted Select of {path} in channel {self.channel}, but"
                f" shows {selected or 'no program'} selected"
            )

    def channel_in_reset(self) -> tuple[bool, str]:
        """Whether the channel is in reset (``chanStatus`` 0), and its state in words."""
        chan = _integer(self.link.read([self.chan_status_node])[0])
        return chan == 0, f"chanStatus {chan} ({CHAN_STATUS.get(chan, '?')})"

    def prepare_run(self, path: str, expected: str, text: str | None = None) -> str:
        """Before a followed run: with the channel in reset, copy ``text`` to ``path``
        (when given) and select ``path``; what the operator is to do next.

        A channel not in reset is left alone: running or stopped with xmalign's
        program (``expected``, e.g. a resumed run) it is followed as it is;
        with another program it is a DeviceError (a stale or wrong program).
        """
        in_reset, state = self.channel_in_reset()
        if not in_reset:
            selected = self.loaded_program()
            if selected is not None and same_program(selected, expected):
                return (
                    f"channel {self.channel} is not in reset ({state}) with xmalign's program"
                    f" {selected}: followed as it is, not selected again"
                )
            raise DeviceError(
                f"{self.name}: channel {self.channel} is not in reset ({state}) with program"
                f" {selected or '(none)'}, not xmalign's program {expected}: a stale or wrong"
                " program? press Reset on the machine, then run again"
            )
        if text is not None:
            self.copy_program(path, text)
        self.select_program(path)
        copied = " (copied to the NC)" if text is not None else ""
        return (
            f"xmalign's program {path}{copied} is selected in channel {self.channel}:"
            " press Cycle Start"
        )

    def copy_program(self, path: str, text: str) -> None:
        """Write ``text`` to the NC as ``path`` (the server's file path), replacing it."""
        folder, method = self.link.find_method("/Methods", "CopyFileToServer")
        self.link.call(
            folder,
            method,
            ua.Variant(path, ua.VariantType.String),
            ua.Variant(text.encode("utf-8"), ua.VariantType.ByteString),
            ua.Variant(True, ua.VariantType.Boolean),
        )

    def _position(self, values: Sequence[Any]) -> Vec:
        try:
            position = np.array([float(v) for v in values]) * self._mm_per_unit
        except (TypeError, ValueError) as error:
            raise DeviceError(f"{self.name} reports a position that is not a number") from error
        if not np.isfinite(position).all():
            raise DeviceError(f"{self.name} reports a position that is not a number: {position}")
        log.debug("%s: machine position %s mm", self.name, np.array2string(position))
        return position


def _integer(value: Any) -> int:
    """An integer state value; -1 when the server sent something else."""
    try:
        return int(value)
    except (TypeError, ValueError):
        return -1


def open_sinumerik(
    endpoint: str,
    timeout_s: float,
    security: OpcUaSecurity,
    channel: int = 1,
    axis_indices: Sequence[int] = (1, 2, 3),
    length_unit: Literal["mm", "inch"] = "mm",
    settle_s: float = 0.2,
    standstill_tolerance_mm: float = 0.002,
    clock: Clock | None = None,
    mode_group: int = 1,
) -> SinumerikMachine:
    """Open a session and read the axes once (one line naming the server on failure)."""
    machine = SinumerikMachine(
        OpcUaLink(endpoint, timeout_s, security),
        channel,
        axis_indices,
        length_unit,
        clock,
        settle_s,
        standstill_tolerance_mm,
        mode_group,
    )
    return machine.open()
