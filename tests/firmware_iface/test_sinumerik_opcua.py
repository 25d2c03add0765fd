"""SINUMERIK over OPC UA: the client against a real OPC UA stack (asyncua's server) on 127.0.0.1.

The server carries the nodes the SINUMERIK OPC UA configuration manual documents
(tests/sinumerik_server.py); the values behind them are set by
the test as the NC would set them.
"""

from __future__ import annotations

import asyncio
import importlib.util
import logging
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from asyncua import Server, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from cli_helpers import free_port
from cryptography.x509.oid import ExtendedKeyUsageOID
from sinumerik_server import SinumerikServer

from firmware_iface.sinumerik_opcua import OpcUaSecurity, open_sinumerik
from sim.clock import SimClock
from xmalign.errors import DeviceError, TransportError, XmalignError
from xmalign.program_check import ProgramGuard

USER = OpcUaSecurity(identity="user", user="xmalign", password="s3cret-Pw")


@pytest.fixture(scope="module")
def served() -> Iterator[SinumerikServer]:
    """One server for the module (asyncua's server takes seconds to build its address space)."""
    server = SinumerikServer(users={"xmalign": "s3cret-Pw"}).start()
    yield server
    server.stop()


@pytest.fixture
def server(served: SinumerikServer) -> SinumerikServer:
    """The module's server, its NC at rest: position 0, reset, no program selected."""
    served.set_position(0.0, 0.0, 0.0)
    served.set("/Channel/State/progStatus[u1]", 5, ua.VariantType.UInt16)
    served.set("/Channel/State/chanStatus[u1]", 0, ua.VariantType.UInt16)
    served.set("/Channel/ProgramInfo/selectedWorkPProg[u1]", "", ua.VariantType.String)
    return served


def test_actual_machine_position_and_program_state(server: SinumerikServer) -> None:
    server.set_position(1250.5, -300.25, 12.0)
    with open_sinumerik(server.endpoint, 5.0, USER) as machine:
        assert np.allclose(machine.position_mm(), [1250.5, -300.25, 12.0])
        status = machine.status()
        assert status.program_state == "idle"
        assert status.state == "progStatus 5 (aborted), chanStatus 0 (reset)"
        assert status.mode == "AUTOMATIC"
        for prog, chan, state in [
            (3, 1, "running"),
            (2, 2, "paused"),
            (1, 2, "paused"),
            (4, 1, "running"),
            (5, 0, "idle"),
        ]:
            server.set("/Channel/State/progStatus[u1]", prog, ua.VariantType.UInt16)
            server.set("/Channel/State/chanStatus[u1]", chan, ua.VariantType.UInt16)
            assert machine.program_state() == state, prog


def test_positions_in_inch_are_converted(server: SinumerikServer) -> None:
    server.set_position(10.0, 1.0, -0.5)
    with open_sinumerik(server.endpoint, 5.0, USER, length_unit="inch") as machine:
        assert np.allclose(machine.position_mm(), [254.0, 25.4, -12.7])


PROGRAM = "Sinumerik/FileSystem/Part Program/XMALIGN.MPF"


@pytest.mark.parametrize("folder", ["/Methods/Filehandling", "/Methods"])
def test_select_a_program_with_the_documented_method(folder: str) -> None:
    """Select's documented status codes, each one line with its meaning; a good one is
    checked against what the NC then shows selected."""
    server = SinumerikServer(users={"xmalign": "s3cret-Pw"}, methods_folder=folder).start()
    try:
        with open_sinumerik(server.endpoint, 5.0, USER) as machine:
            assert machine.loaded_program() is None
            machine.select_program(PROGRAM)
            assert machine.loaded_program() == "/_N_MPF_DIR/_N_XMALIGN_MPF"
            assert server.select_calls == [(PROGRAM, 1)]
            nope = "Sinumerik/FileSystem/Part Program/NOPE.MPF"
            with pytest.raises(
                DeviceError,
                match=f"did not select {nope} in channel 1: Select answered 2 .program not found",
            ):
                machine.select_program(nope)
            server.refuse_select = True
            with pytest.raises(DeviceError, match=r"answered 4 \(refused by the NC\)"):
                machine.select_program(PROGRAM)
            server.set("/Channel/State/chanStatus[u1]", 1, ua.VariantType.UInt16)
            with pytest.raises(DeviceError, match=r"answered 3 \(channel not in reset\)"):
                machine.select_program(PROGRAM)
    finally:
        server.stop()


def test_a_select_the_nc_does_not_show_is_refused(server: SinumerikServer) -> None:
    """Select answers 0 but the NC shows no program selected: refused, not taken on trust."""
    server.select_ignored = True
    try:
        with (
            open_sinumerik(server.endpoint, 5.0, USER) as machine,
            pytest.raises(DeviceError, match="accepted Select of .* shows no program"),
        ):
            machine.select_program(PROGRAM)
    finally:
        server.select_ignored = False


def test_the_program_report_is_the_selected_program_and_its_state(
    server: SinumerikServer,
) -> None:
    with open_sinumerik(server.endpoint, 5.0, USER) as machine:
        report = machine.program_report()
        assert report.name is None and report.state == "idle"
        machine.select_program(PROGRAM)
        server.set("/Channel/State/progStatus[u1]", 3, ua.VariantType.UInt16)
        report = machine.program_report()
        assert (report.name, report.state) == ("/_N_MPF_DIR/_N_XMALIGN_MPF", "running")


def test_before_a_run_the_program_is_copied_and_selected_in_reset(server: SinumerikServer) -> None:
    target = "Sinumerik/FileSystem/Part Program/RUN.MPF"
    with open_sinumerik(server.endpoint, 5.0, USER) as machine:
        told = machine.prepare_run(target, target, "; RUN\nM30\n")
        assert server.programs[target] == b"; RUN\nM30\n"
        assert machine.loaded_program() == "/_N_MPF_DIR/_N_RUN_MPF"
        assert told.endswith("(copied to the NC) is selected in channel 1: press Cycle Start")
        # a resumed run: the channel runs xmalign's program; left as it is, not copied again
        server.set("/Channel/State/chanStatus[u1]", 1, ua.VariantType.UInt16)
        told = machine.prepare_run(target, "run", "; CHANGED\n")
        assert "followed as it is, not selected again" in told
        assert server.programs[target] == b"; RUN\nM30\n"


def test_a_channel_not_in_reset_with_another_program_is_one_line(server: SinumerikServer) -> None:
    server.set("/Channel/State/chanStatus[u1]", 2, ua.VariantType.UInt16)
    server.set(
        "/Channel/ProgramInfo/selectedWorkPProg[u1]",
        "/_N_MPF_DIR/_N_OLD_MPF",
        ua.VariantType.String,
    )
    calls = len(server.select_calls)
    with (
        open_sinumerik(server.endpoint, 5.0, USER) as machine,
        pytest.raises(DeviceError) as caught,
    ):
        machine.prepare_run(PROGRAM, PROGRAM)
    assert str(caught.value) == (
        f"the SINUMERIK OPC UA server at {server.endpoint}: channel 1 is not in reset"
        " (chanStatus 2 (interrupted)) with program /_N_MPF_DIR/_N_OLD_MPF, not xmalign's"
        f" program {PROGRAM}: a stale or wrong program? press Reset on the machine, then run"
        " again"
    )
    assert len(server.select_calls) == calls  # nothing selected behind the operator's back


def test_copying_without_the_file_write_right_is_one_line(server: SinumerikServer) -> None:
    server.may_write_files = False
    try:
        with (
            open_sinumerik(server.endpoint, 5.0, USER) as machine,
            pytest.raises(DeviceError, match="BadUserAccessDenied") as caught,
        ):
            machine.copy_program(PROGRAM, "M30\n")
        assert "\n" not in str(caught.value) and "CopyFileToServer" in str(caught.value)
    finally:
        server.may_write_files = True


def test_a_wrong_password_is_refused_and_never_shown(
    server: SinumerikServer, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG)
    wrong = OpcUaSecurity(identity="user", user="xmalign", password="not-the-Pw-42")
    with pytest.raises(
        DeviceError,
        match=f"cannot open a session with the SINUMERIK OPC UA server at {server.endpoint}: Bad",
    ) as caught:
        open_sinumerik(server.endpoint, 5.0, wrong)
    assert "not-the-Pw-42" not in str(caught.value) and "\n" not in str(caught.value)
    assert "not-the-Pw-42" not in repr(wrong)
    assert not _records_with("not-the-Pw-42", caplog)


def _records_with(secret: str, caplog: pytest.LogCaptureFixture) -> list[str]:
    """Records of the client side (xmalign, asyncua's client) that show ``secret``.

    The test's own server (asyncua.server) dumps requests at DEBUG; it is not
    part of xmalign and never runs in its process.
    """
    return [
        r.name
        for r in caplog.records
        if secret in r.getMessage() and not r.name.startswith("asyncua.server")
    ]


def test_the_password_is_never_logged(
    server: SinumerikServer, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG)
    with open_sinumerik(server.endpoint, 5.0, USER) as machine:
        machine.status()
    assert "> read /Channel/MachineAxis/actToolBasePos[u1,1]" in caplog.text
    assert "as 'xmalign'" in caplog.text
    assert any(
        r.name.startswith("asyncua.client") and r.levelno == logging.DEBUG for r in caplog.records
    )  # asyncua dumped its requests, the password masked
    assert not _records_with("s3cret-Pw", caplog)


def test_a_missing_axis_node_names_the_node(server: SinumerikServer) -> None:
    node = "ns=2;s=/Channel/MachineAxis/actToolBasePos[u1,4]"
    with pytest.raises(DeviceError, match=re.escape(f"refused to read {node} (BadNodeIdUnknown)")):
        open_sinumerik(server.endpoint, 5.0, USER, axis_indices=(1, 2, 4))


def test_an_unreachable_server_is_a_transport_error() -> None:
    endpoint = f"opc.tcp://127.0.0.1:{free_port()}"
    with pytest.raises(
        TransportError,
        match=f"cannot open a session with the SINUMERIK OPC UA server at {endpoint}",
    ):
        open_sinumerik(endpoint, 2.0, USER)


def test_a_server_gone_mid_run_is_a_transport_error() -> None:
    server = SinumerikServer(users={"xmalign": "s3cret-Pw"}).start()
    machine = open_sinumerik(server.endpoint, 2.0, USER)
    server.stop()
    try:
        with pytest.raises(TransportError, match="the SINUMERIK OPC UA server at"):
            machine.position_mm()
    finally:
        machine.close()


def test_standstill_over_the_settle_time(server: SinumerikServer) -> None:
    clock = SimClock()
    with open_sinumerik(server.endpoint, 5.0, USER, settle_s=0.5, clock=clock) as machine:
        seen = []
        for x in [10.0, 10.5, 11.0, 11.0, 11.001, 11.0, 11.0]:
            server.set_position(x, 0.0, 0.0)
            seen.append(machine.is_standstill())
            clock.sleep(0.2)
        assert seen == [False, False, False, False, False, True, True]


@pytest.fixture(scope="module")
def certificates(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Self-signed certificates for the server and for xmalign (asyncua's generator)."""
    folder = tmp_path_factory.mktemp("pki")
    files = {}
    for who, use in [
        ("server", ExtendedKeyUsageOID.SERVER_AUTH),
        ("client", ExtendedKeyUsageOID.CLIENT_AUTH),
    ]:
        key, cert = folder / f"{who}-key.pem", folder / f"{who}-cert.der"
        asyncio.run(
            setup_self_signed_certificate(
                key, cert, f"urn:xmalign:test:{who}", "127.0.0.1", [use], {"commonName": who}
            )
        )
        files[f"{who}_key"], files[f"{who}_cert"] = key, cert
    return files


def test_an_encrypted_session_with_certificate_and_password(certificates: dict[str, Path]) -> None:
    async def secure(server: Server) -> None:
        await server.load_certificate(str(certificates["server_cert"]))
        await server.load_private_key(str(certificates["server_key"]))
        server.set_security_policy([ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt])

    server = SinumerikServer(users={"xmalign": "s3cret-Pw"}, configure=secure).start()
    try:
        security = OpcUaSecurity(
            policy="Basic256Sha256",
            certificate=certificates["client_cert"],
            private_key=certificates["client_key"],
            identity="user",
            user="xmalign",
            password="s3cret-Pw",
        )
        server.set_position(1.0, 2.0, 3.0)
        with open_sinumerik(server.endpoint, 5.0, security) as machine:
            assert np.allclose(machine.position_mm(), [1.0, 2.0, 3.0])
        plain = OpcUaSecurity(identity="user", user="xmalign", password="s3cret-Pw")
        with pytest.raises(XmalignError, match="cannot open a session with"):
            open_sinumerik(server.endpoint, 5.0, plain)  # the server offers no unencrypted endpoint
        as_certificate = OpcUaSecurity(
            policy="Basic256Sha256",
            certificate=certificates["client_cert"],
            private_key=certificates["client_key"],
            identity="certificate",
        )
        with open_sinumerik(server.endpoint, 5.0, as_certificate) as machine:
            assert machine.program_state() == "idle"
    finally:
        server.stop()


@pytest.mark.skipif(
    importlib.util.find_spec("o6") is None, reason="o6 (open62541 for Python) not installed"
)
def test_cross_check_against_open62541() -> None:
    """The same client against another OPC UA stack: open62541, through PyPI's o6.

    o6's free build ends its process ten minutes after the import, so the server
    runs in a process of its own (tests/firmware_iface/o6_sinumerik_server.py);
    o6 is not among the project's dependencies (docs/hardware.md).
    """
    port = free_port()
    script = Path(__file__).with_name("o6_sinumerik_server.py")
    server = subprocess.Popen(
        [sys.executable, str(script), str(port)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        assert server.stdout is not None
        banner = iter(server.stdout.readline, "")  # o6 prints its banner first
        assert any(line.strip() == "READY" for line in banner), "the o6 server did not start"
        with open_sinumerik(f"opc.tcp://127.0.0.1:{port}", 5.0, OpcUaSecurity()) as machine:
            assert np.allclose(machine.position_mm(), [1250.5, -300.25, -42.0])
            status = machine.status()
            assert (status.program_state, status.mode) == ("running", "AUTOMATIC")
            assert status.state == "progStatus 3 (in progress), chanStatus 1 (active)"
            assert machine.loaded_program() == "/_N_MPF_DIR/_N_XMALIGN_MPF"
            report = machine.program_report()
            assert (report.name, report.state) == ("/_N_MPF_DIR/_N_XMALIGN_MPF", "running")
            ProgramGuard(machine, "XMALIGN", "key", print).check()  # xmalign's: passes
            with pytest.raises(DeviceError, match="not xmalign's program run"):
                ProgramGuard(machine, "run", "key", print).check()
    finally:
        server.communicate(input="", timeout=30)
