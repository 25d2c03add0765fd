"""An OPC UA server (asyncua) on 127.0.0.1 carrying the SINUMERIK address space as documented.

The nodes are those the SINUMERIK OPC UA configuration manual names for NC
access (namespace 2, string identifiers such as
``/Channel/MachineAxis/actToolBasePos[u1,1]``) and the ``Select`` and
``CopyFileToServer`` methods under ``/Methods/Filehandling`` (manual 05/2022,
7.5 and 7.6) or directly under ``/Methods`` (earlier versions), with their
documented arguments and Select's status codes (0 good, 1 channel not found, 2
program not found, 3 channel not in reset, 4 refused). A selected program shows
in ``selectedWorkPProg`` in the NC notation (``Sinumerik/FileSystem/Part
Program/RUN.MPF`` selected: ``/_N_MPF_DIR/_N_RUN_MPF``), as the programming
manual has the NC name its files (our reading: not seen on a controller). A
real OPC UA stack (asyncua's server) answers; what a real NC does behind the
nodes (moving axes, a channel not in reset) the test sets.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

from asyncua import Server, ua
from asyncua.crypto.permission_rules import User, UserRole
from asyncua.server.user_managers import UserManager
from cli_helpers import free_port

NS = 2
PART_PROGRAMS = "Sinumerik/FileSystem/Part Program/"
#: Where the NC keeps each folder of the OPC UA file system (NC notation).
NC_FOLDERS = {PART_PROGRAMS: "/_N_MPF_DIR/"}


def nc_notation(path: str) -> str:
    """``Sinumerik/FileSystem/Part Program/run.mpf`` -> ``/_N_MPF_DIR/_N_RUN_MPF``."""
    folder, _, name = path.rpartition("/")
    stem, _, extension = name.rpartition(".")
    return f"{NC_FOLDERS[folder + '/']}_N_{stem.upper()}_{extension.upper()}"


class PasswordUsers(UserManager):
    """Users with passwords (the SINUMERIK server's user administration)."""

    def __init__(self, users: dict[str, str]) -> None:
        self.users = users

    def get_user(
        self,
        iserver: Any,
        username: str | None = None,
        password: str | None = None,
        certificate: Any = None,
    ) -> User | None:
        if username is not None:
            known = self.users.get(username) == password
            return User(role=UserRole.User, name=username) if known else None
        if certificate:  # the secure channel's certificate, with an X509 identity token
            return User(role=UserRole.User, name="certificate")
        return None


class SinumerikServer:
    """The documented SINUMERIK nodes, served by asyncua on 127.0.0.1 in a thread of its own.

    Parameters
    ----------
    users : dict, optional
        User name -> password; when given, anonymous sessions are refused.
    methods_folder : str
        Where ``Select`` is: ``/Methods/Filehandling`` or ``/Methods``.
    configure : callable, optional
        ``configure(server)`` before start (security policies, certificates).
    """

    def __init__(
        self,
        users: dict[str, str] | None = None,
        methods_folder: str = "/Methods/Filehandling",
        configure: Callable[[Server], Any] | None = None,
        axes: int = 3,
    ) -> None:
        self.users = users
        self.methods_folder = methods_folder
        self.configure = configure
        self.axes = axes
        self.port = free_port()
        self.endpoint = f"opc.tcp://127.0.0.1:{self.port}"
        #: The NC's part programs: path in the OPC UA file system -> content.
        self.programs: dict[str, bytes] = {f"{PART_PROGRAMS}XMALIGN.MPF": b"M30\n"}
        self.select_calls: list[tuple[str, int]] = []
        #: The NC refuses a selection (Select's status 4), the user lacks FsWrite.
        self.refuse_select = False
        self.may_write_files = True
        #: Select answers 0 but selects nothing (a server not doing what it says).
        self.select_ignored = False
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, daemon=True)
        self._server: Server | None = None
        self._nodes: dict[str, Any] = {}

    def start(self) -> SinumerikServer:
        self._thread.start()
        self._run(self._start()).result(timeout=30)
        return self

    def stop(self) -> None:
        if self._server is not None:
            self._run(self._server.stop()).result(timeout=30)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=10)
        self._loop.close()

    def set(self, node_id: str, value: Any, variant: ua.VariantType) -> None:
        """Write a node's value as the NC would (thread-safe)."""
        node = self._nodes[node_id]
        self._run(node.write_value(ua.Variant(value, variant))).result(timeout=10)

    def set_position(self, x: float, y: float, z: float) -> None:
        for axis, value in enumerate((x, y, z), start=1):
            self.set(
                f"/Channel/MachineAxis/actToolBasePos[u1,{axis}]", value, ua.VariantType.Double
            )

    def value(self, node_id: str) -> Any:
        return self._run(self._nodes[node_id].read_value()).result(timeout=10)

    def _run(self, coroutine: Any) -> Future[Any]:
        return asyncio.run_coroutine_threadsafe(coroutine, self._loop)

    async def _start(self) -> None:
        manager = PasswordUsers(self.users) if self.users is not None else None
        server = Server(user_manager=manager)
        await server.init()
        server.set_endpoint(f"{self.endpoint}/")
        server.set_server_name("SINUMERIK OPC UA server (test stand-in)")
        if self.users is not None:
            server.set_identity_tokens([ua.UserNameIdentityToken, ua.X509IdentityToken])
        if self.configure is not None:
            await _maybe_await(self.configure(server))
        index = await server.register_namespace("SinumerikVarProvider")
        assert index == NS, index
        sinumerik = await server.nodes.objects.add_object(ua.NodeId("Sinumerik", NS), "Sinumerik")
        variables: list[tuple[str, Any, ua.VariantType]] = [
            *(
                (f"/Channel/MachineAxis/actToolBasePos[u1,{i}]", 0.0, ua.VariantType.Double)
                for i in range(1, self.axes + 1)
            ),
            ("/Channel/State/progStatus[u1]", 5, ua.VariantType.UInt16),
            ("/Channel/State/chanStatus[u1]", 0, ua.VariantType.UInt16),
            ("/Channel/ProgramInfo/selectedWorkPProg[u1]", "", ua.VariantType.String),
            ("/Bag/State/opMode[u1]", 2, ua.VariantType.UInt16),
        ]
        for node_id, value, variant in variables:
            self._nodes[node_id] = await sinumerik.add_variable(
                ua.NodeId(node_id, NS), node_id, ua.Variant(value, variant)
            )
        methods = await sinumerik.add_object(ua.NodeId("/Methods", NS), "Methods")
        if self.methods_folder != "/Methods":
            methods = await methods.add_object(
                ua.NodeId(self.methods_folder, NS), self.methods_folder.rsplit("/", 1)[-1]
            )
        await methods.add_method(
            ua.NodeId(f"{self.methods_folder}/Select", NS),
            ua.QualifiedName("Select", NS),
            self._select,
            [ua.VariantType.String, ua.VariantType.Int32],
            [ua.VariantType.Int32],
        )
        await methods.add_method(
            ua.NodeId(f"{self.methods_folder}/CopyFileToServer", NS),
            ua.QualifiedName("CopyFileToServer", NS),
            self._copy_file_to_server,
            [ua.VariantType.String, ua.VariantType.ByteString, ua.VariantType.Boolean],
            [],
        )
        await server.start()
        self._server = server

    async def _select(self, parent: ua.NodeId, path: ua.Variant, channel: ua.Variant) -> list:
        """The documented status codes: 0 good, 1 channel, 2 program, 3 not in reset, 4
        refused; a good one selects the program (selectedWorkPProg in NC notation)."""
        self.select_calls.append((path.Value, channel.Value))
        if channel.Value != 1:
            status = 1
        elif path.Value not in self.programs:
            status = 2
        elif await self._nodes["/Channel/State/chanStatus[u1]"].read_value() != 0:
            status = 3
        elif self.refuse_select:
            status = 4
        elif self.select_ignored:
            status = 0
        else:
            status = 0
            await self._nodes["/Channel/ProgramInfo/selectedWorkPProg[u1]"].write_value(
                ua.Variant(nc_notation(path.Value), ua.VariantType.String)
            )
        return [ua.Variant(status, ua.VariantType.Int32)]

    async def _copy_file_to_server(
        self, parent: ua.NodeId, target: ua.Variant, data: ua.Variant, overwrite: ua.Variant
    ) -> list | ua.StatusCode:
        """Store the file; without the FsWrite right the call is refused."""
        if not self.may_write_files:
            return ua.StatusCode(ua.StatusCodes.BadUserAccessDenied)
        if target.Value in self.programs and not overwrite.Value:
            return ua.StatusCode(ua.StatusCodes.BadAlreadyExists)
        self.programs[target.Value] = data.Value
        return []


async def _maybe_await(value: Any) -> None:
    if asyncio.iscoroutine(value):
        await value
