"""units.yaml: machine_position from an MTConnect agent or a SINUMERIK, opened from the file."""

from __future__ import annotations

import re
import textwrap
from collections.abc import Iterator
from pathlib import Path
from typing import get_args

import numpy as np
import pytest
from cli_helpers import free_port
from mtconnect_agent import TestAgent
from pydantic import BaseModel
from sinumerik_server import SinumerikServer

from firmware_iface.config import UnitsConfig, load_units_config, open_devices
from firmware_iface.controller_config import (
    MTConnectConfig,
    SinumerikConfig,
    expected_program,
    open_sinumerik_source,
)
from sim.clock import SimClock
from sim.servers.modbus import ModbusUnitServer
from sim.units import SimUnit
from xmalign.errors import InputError, TransportError
from xmalign.formats.common import is_secret_field

ROOT = Path(__file__).resolve().parents[2]
HEAD = """\
format: xmalign.units/1
launch: {{transport: modbus-tcp, host: 127.0.0.1, port: {launch}}}
receiver: {{transport: modbus-tcp, host: 127.0.0.1, port: {receiver}}}
interferometer: {{replay: stream.csv}}
"""


@pytest.mark.parametrize("name", ["units-mtconnect.yaml", "units-sinumerik.yaml"])
def test_the_documented_examples_load_and_are_in_the_docs(name: str) -> None:
    example = ROOT / "examples" / name
    config = load_units_config(example)
    assert config.machine_position.follows_the_machine
    docs = (ROOT / "docs" / "hardware.md").read_text(encoding="utf-8")
    assert example.read_text(encoding="utf-8") in docs, f"docs/hardware.md lost {name}"


def test_certificate_paths_are_relative_to_the_file() -> None:
    sinumerik = load_units_config(ROOT / "examples" / "units-sinumerik.yaml").machine_position
    assert sinumerik.sinumerik is not None
    assert sinumerik.sinumerik.certificate == ROOT / "examples" / "xmalign-cert.der"
    assert sinumerik.sinumerik.login == "user"


@pytest.mark.parametrize(
    ("section", "fragment"),
    [
        ("source: mtconnect", "'mtconnect' is required with source: mtconnect"),
        ("source: mtconnect\n  mtconnect: {url: 'ftp://agent'}", "machine_position.mtconnect.url"),
        ("source: mtconnect\n  mtconnect: {url: 'http://a', axes: [X, Y]}", "mtconnect.axes"),
        ("source: sinumerik\n  sinumerik: {endpoint: 'http://h'}", "sinumerik.endpoint"),
        (
            "source: sinumerik\n  sinumerik: {endpoint: 'opc.tcp://h:4840', "
            "security_policy: Basic256Sha256}",
            "security_policy Basic256Sha256 needs 'certificate'",
        ),
        (
            "source: sinumerik\n  sinumerik: {endpoint: 'opc.tcp://h:4840', certificate: c.der}",
            "give both 'certificate' and 'private_key'",
        ),
        (
            "source: sinumerik\n  sinumerik: {endpoint: 'opc.tcp://h:4840', user: u, "
            "password: p, password_env: P}",
            "'password' or 'password_env', not both",
        ),
        ("source: file\n  file: p.txt\n  mtconnect: {url: 'http://a'}", "'mtconnect' is required"),
    ],
)
def test_bad_controller_sections_name_the_file_and_key(
    tmp_path: Path, section: str, fragment: str
) -> None:
    path = tmp_path / "units.yaml"
    path.write_text(HEAD.format(launch=1, receiver=2) + f"machine_position:\n  {section}\n")
    with pytest.raises(InputError, match=f"units.yaml: .*{re.escape(fragment)}") as caught:
        load_units_config(path)
    assert "\n" not in str(caught.value)


def test_a_password_is_never_shown_by_the_configuration(tmp_path: Path) -> None:
    path = tmp_path / "units.yaml"
    path.write_text(
        HEAD.format(launch=1, receiver=2)
        + "machine_position:\n  source: sinumerik\n  sinumerik: {endpoint: 'opc.tcp://h:4840',"
        " user: u, password: Hunter-22}\n"
    )
    config = load_units_config(path)
    assert "Hunter-22" not in repr(config) and "Hunter-22" not in str(config)


@pytest.fixture
def two_units() -> Iterator[tuple[int, int]]:
    """A launch and a receiver unit served over Modbus TCP on 127.0.0.1: their ports."""
    servers = [
        ModbusUnitServer(SimUnit(kind, SimClock(real_time=True)), "127.0.0.1", free_port())
        for kind in ("launch", "receiver")
    ]
    for server in servers:
        server.start()
    yield servers[0].port, servers[1].port
    for server in servers:
        server.stop()


def _units_file(tmp_path: Path, ports: tuple[int, int], machine_position: str) -> Path:
    (tmp_path / "stream.csv").write_text(
        "time_s,linear_um,straightness_v_um,straightness_w_um,angle_u_urad,"
        "angle_v_urad,angle_w_urad,beam_ok\n0,0,1,2,3,4,5,1\n"
    )
    path = tmp_path / "units.yaml"
    path.write_text(
        HEAD.format(launch=ports[0], receiver=ports[1]) + textwrap.dedent(machine_position)
    )
    return path


def test_open_devices_follows_an_mtconnect_agent(
    reference_machine,  # noqa: ANN001
    two_units: tuple[int, int],
    tmp_path: Path,
) -> None:
    agent = TestAgent("linuxcnc", "LinuxCNC").start()
    try:
        agent.set(X=1000.0, Y=750.0, Z=250.0)
        section = f"""\
            machine_position:
              source: mtconnect
              mtconnect: {{url: '{agent.url}', device: LinuxCNC, timeout_s: 2.0}}
            """
        path = _units_file(tmp_path, two_units, section)
        devices = open_devices(load_units_config(path), reference_machine, input, print)
        try:
            assert np.allclose(devices.mover.position_mm(), [1000.0, 750.0, 250.0])
        finally:
            devices.close()
    finally:
        agent.stop()
    # no agent there: one line naming it, and the units opened before are closed again
    path = _units_file(tmp_path, two_units, section)
    with pytest.raises(TransportError, match=f"cannot reach the MTConnect agent at {agent.url}"):
        open_devices(load_units_config(path), reference_machine, input, print)
    devices = open_devices(  # the units took no harm: they open again
        load_units_config(_units_file(tmp_path, two_units, "")), reference_machine, input, print
    )
    devices.close()


def test_open_a_sinumerik_with_the_password_from_the_environment(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    server = SinumerikServer(users={"xmalign": "s3cret-Pw"}).start()
    try:
        server.set_position(5.0, 6.0, 7.0)
        path = _units_file(
            tmp_path,
            (1, 2),
            f"""\
            machine_position:
              source: sinumerik
              sinumerik: {{endpoint: '{server.endpoint}', user: xmalign,
                           password_env: XMALIGN_TEST_PW, timeout_s: 5.0}}
            """,
        )
        section = load_units_config(path).machine_position.sinumerik
        assert section is not None
        closers: list = []
        with pytest.raises(InputError, match="environment variable XMALIGN_TEST_PW is not set"):
            open_sinumerik_source(section, 1.0, closers)
        monkeypatch.setenv("XMALIGN_TEST_PW", "s3cret-Pw")
        machine = open_sinumerik_source(section, 1.0, closers)
        try:
            assert np.allclose(machine.position_mm(), [5.0, 6.0, 7.0])
        finally:
            for close in closers:
                close()
    finally:
        server.stop()


def test_xmalign_s_program_is_named_by_the_key_then_the_nc_path_then_the_default() -> None:
    agent = MTConnectConfig(url="http://a")
    assert expected_program(agent, "run") == (
        "run",
        "machine_position.mtconnect.program_name, default: the program file's name",
    )
    named = MTConnectConfig(url="http://a", program_name="O1000")
    assert expected_program(named, "run") == ("O1000", "machine_position.mtconnect.program_name")
    path = "Sinumerik/FileSystem/Part Program/XMALIGN.MPF"
    nc = SinumerikConfig(endpoint="opc.tcp://h:4840", program=path)
    assert expected_program(nc, "run") == (path, "machine_position.sinumerik.program")
    both = SinumerikConfig(endpoint="opc.tcp://h:4840", program=path, program_name="CAL")
    assert expected_program(both, "run") == ("CAL", "machine_position.sinumerik.program_name")


def _secret_keys(model: type[BaseModel], prefix: str = "") -> set[str]:
    """Every secret field reachable in ``model`` (dotted keys)."""
    keys = set()
    for name, field in model.model_fields.items():
        if is_secret_field(field):
            keys.add(prefix + name)
        for inner in _models(field.annotation):
            keys |= _secret_keys(inner, f"{prefix}{name}.")
    return keys


def _models(annotation: object) -> list[type[BaseModel]]:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [model for argument in get_args(annotation) for model in _models(argument)]


#: A valid section around each secret key of units.yaml (the key's value goes at {}).
SECRET_SECTIONS = {
    "machine_position.sinumerik.password": (
        "source: sinumerik\n  sinumerik: {{endpoint: 'opc.tcp://h:4840', user: u, password: {}}}"
    ),
    "machine_position.linuxcncrsh.connect_password": (
        "source: linuxcncrsh\n  linuxcncrsh: {{host: h, program: p.ngc, connect_password: {}}}"
    ),
    "machine_position.linuxcncrsh.enable_password": (
        "source: linuxcncrsh\n  linuxcncrsh: {{host: h, program: p.ngc, enable_password: {}}}"
    ),
}


def test_every_secret_key_is_in_the_bad_value_table() -> None:
    assert _secret_keys(UnitsConfig) == set(SECRET_SECTIONS)


def _units_with(tmp_path: Path, section: str) -> Path:
    path = tmp_path / "units.yaml"
    path.write_text(HEAD.format(launch=1, receiver=2) + f"machine_position:\n  {section}\n")
    return path


@pytest.mark.parametrize("key", sorted(SECRET_SECTIONS))
@pytest.mark.parametrize(
    ("value", "shown"),
    [
        ("yes", "True"),
        ("4711.5", "4711.5"),
        ("[4711, 815]", "4711"),
        ("{pin: 4711}", "4711"),
        ("'s3cr3t-but-\u00e4'", "s3cr3t"),  # linuxcncrsh: ASCII only
        ("'two words'", "two"),  # linuxcncrsh: one word
        ("0123", "123"),  # YAML 1.1: the octal number 83
        ("12:34", "12:34"),  # YAML 1.1: 754, in base 60
    ],
)
def test_a_bad_secret_is_refused_without_showing_it(
    tmp_path: Path, key: str, value: str, shown: str
) -> None:
    path = _units_with(tmp_path, SECRET_SECTIONS[key].format(value))
    if "linuxcncrsh" not in key and value.startswith("'"):
        load_units_config(path)  # OPC UA takes any text
        return
    with pytest.raises(InputError, match=f"units.yaml: key '{re.escape(key)}'") as caught:
        load_units_config(path)
    message = str(caught.value)
    assert shown not in message and "\n" not in message
    assert caught.value.__cause__ is None  # pydantic's message shows the input: not chained


@pytest.mark.parametrize("key", sorted(SECRET_SECTIONS))
def test_a_whole_number_is_a_password_as_written(tmp_path: Path, key: str) -> None:
    config = load_units_config(_units_with(tmp_path, SECRET_SECTIONS[key].format("4711")))
    section = config.machine_position.sinumerik or config.machine_position.linuxcncrsh
    secret = getattr(section, key.rsplit(".", 1)[1])
    assert secret.get_secret_value() == "4711" and "4711" not in repr(config)


def test_linuxcncrsh_passwords_from_the_file_the_environment_or_the_defaults(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    section = (
        "source: linuxcncrsh\n  linuxcncrsh: {host: h, program: p.ngc, connect_password: 4711,"
        " enable_password_env: XMALIGN_TEST_ENABLE}"
    )
    rsh = load_units_config(_units_with(tmp_path, section)).machine_position.linuxcncrsh
    assert rsh is not None
    with pytest.raises(InputError, match="enable_password_env: the environment variable"):
        rsh.passwords()
    monkeypatch.setenv("XMALIGN_TEST_ENABLE", "from-env")
    assert rsh.passwords() == ("4711", "from-env")
    bare = "source: linuxcncrsh\n  linuxcncrsh: {host: h, program: p.ngc}"
    rsh = load_units_config(_units_with(tmp_path, bare)).machine_position.linuxcncrsh
    assert rsh is not None and rsh.passwords() == ("EMC", "EMCTOO")
    both = (
        "source: linuxcncrsh\n  linuxcncrsh: {host: h, program: p.ngc, connect_password: a,"
        " connect_password_env: B}"
    )
    with pytest.raises(InputError, match="'connect_password' or 'connect_password_env'"):
        load_units_config(_units_with(tmp_path, both))
