"""The hardware configuration ``units.yaml`` of ``--live`` runs, and opening what it names.

    format: xmalign.units/1
    launch:                        # one positioning unit: Modbus TCP, Modbus RTU or CANopen
      transport: modbus-tcp
      host: 192.168.10.11
      port: 502                    # default 502
      device_id: 1                 # default 1
    receiver:
      transport: canopen
      interface: socketcan         # python-can interface
      channel: can0
      bitrate: 500000              # default 500000
      node_ids: [3, 4, 5]          # default: the axis numbers a3, a4, a5
      # interface: udp_local       # the simulated bus of `xmalign sim serve --canopen GROUP`
      # host: 127.0.0.1            # udp_local only: the interface it runs on (default loopback)
      # hop_limit: 0               # udp_local, udp_multicast: TTL, default 0 (this computer only)
    interferometer:
      port: /dev/ttyUSB0           # or a pyserial URL (socket://host:port)
      baudrate: 115200             # default 115200
      rate_hz: 50                  # default 50
      # replay: recorded.csv       # instead of port: play back a recorded stream
    machine_position:
      source: prompt               # prompt (operator types it), file, linuxcncrsh, linuxcnc,
      #                              mtconnect or sinumerik
      # file: /mnt/cnc/position.txt  (source: file; the operator still moves the machine)
      # linuxcncrsh: {host: 192.168.10.20, program: /mnt/cnc/xmalign-run.ngc,
      #               enable_password_env: XMALIGN_LINUXCNC_ENABLE_PW}
      #                            (source: linuxcncrsh; xmalign runs the program itself;
      #                             examples/units-linuxcncrsh.yaml has every key)
      # linuxcnc: {program: /home/cnc/xmalign-run.ngc}
      #                            (source: linuxcnc: the same, through LinuxCNC's Python
      #                             module, xmalign on the CNC's own computer)
      # mtconnect: {url: http://192.168.10.30:5000, device: VMC}
      # sinumerik: {endpoint: opc.tcp://192.168.214.241:4840, user: xmalign,
      #             password_env: XMALIGN_OPCUA_PASSWORD}
      #   (mtconnect, sinumerik: read-only, the operator runs the program; every key
      #   in firmware_iface/controller_config.py)
    timeouts:
      io_s: 1.0                    # one request to a device
      move_s: 30.0                 # one unit move
      machine_s: 600.0             # the machine reaching its next stop (a run on a controller)
    environment:                   # optional; see docs/environment.md
      source: serial               # fixed, file, serial, modbus-tcp or modbus-rtu
      port: /dev/ttyUSB1
      serial: XC80-0042            # for the calibration record
    instruments:                   # optional serial numbers for the calibration record
      interferometer: XM60-1234

A Modbus RTU unit has ``transport: modbus-rtu``, ``serial_port`` and
``baudrate``. Every error names the file and the key (exit code 2).
See docs/hardware.md and examples/units.yaml.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import canopen
from pydantic import Field, SecretStr, ValidationInfo, field_validator, model_validator

from firmware_iface.can_bus import (
    LOOPBACK,
    UDP_LOCAL,
    check_interface,
    multicast_group,
    open_can_bus,
)
from firmware_iface.canopen_axis import CanopenUnit, unit_node_ids
from firmware_iface.controller_config import (
    MTConnectConfig,
    Seconds,
    SinumerikConfig,
    open_mtconnect_source,
    open_sinumerik_source,
    resolve_paths,
    secret_value,
)
from firmware_iface.interferometer import ReplayInterferometer, SerialInterferometer, open_serial
from firmware_iface.linuxcnc_control import START_TIMEOUT_S, LinuxCncControl, MdiMover
from firmware_iface.linuxcnc_module import open_local_linuxcnc
from firmware_iface.linuxcncrsh import (
    DEFAULT_CONNECT_PASSWORD,
    DEFAULT_ENABLE_PASSWORD,
    DEFAULT_PORT,
    check_password,
    open_linuxcnc,
)
from firmware_iface.machine_position import FilePositions, OperatorPrompt
from firmware_iface.modbus import ModbusUnit, rtu_transport, tcp_transport
from firmware_iface.weather_station import (
    EnvironmentConfig,
    open_environment,
    resolve_environment,
)
from xmalign.errors import InputError
from xmalign.formats.common import (
    Secret,
    StrictFileModel,
    check_format,
    located,
    read_yaml,
    validate,
)
from xmalign.machine import Machine
from xmalign.roles import (
    Clock,
    ClosesOnExit,
    EnvironmentSource,
    Interferometer,
    MachineMover,
    MachinePositionSource,
    PositioningUnit,
)

UNITS_FORMAT = "xmalign.units/1"


_Strict = StrictFileModel


class ModbusTcpUnit(_Strict):
    transport: Literal["modbus-tcp"]
    host: str
    port: Annotated[int, Field(ge=1, le=65535)] = 502
    device_id: Annotated[int, Field(ge=0, le=247)] = 1


class ModbusRtuUnit(_Strict):
    transport: Literal["modbus-rtu"]
    serial_port: str
    baudrate: Annotated[int, Field(gt=0)] = 115200
    device_id: Annotated[int, Field(ge=1, le=247)] = 1


class CanopenUnitConfig(_Strict):
    transport: Literal["canopen"]
    interface: str = "socketcan"
    channel: str
    bitrate: Annotated[int, Field(gt=0)] = 500000
    node_ids: list[Annotated[int, Field(ge=1, le=127)]] | None = None
    #: udp_local only: IPv4 address of the network interface the bus runs on.
    host: str = LOOPBACK
    #: udp_local and udp_multicast: TTL of the frames; 0 keeps the bus on this computer.
    hop_limit: Annotated[int, Field(ge=0, le=255)] = 0

    @field_validator("interface")
    @classmethod
    def _known_interface(cls, interface: str) -> str:
        check_interface(interface)
        return interface

    @field_validator("channel")
    @classmethod
    def _group_of_udp_local(cls, channel: str, info: ValidationInfo) -> str:
        return multicast_group(channel) if info.data.get("interface") == UDP_LOCAL else channel


UnitConfig = Annotated[
    ModbusTcpUnit | ModbusRtuUnit | CanopenUnitConfig, Field(discriminator="transport")
]


class InterferometerConfig(_Strict):
    port: str | None = None
    baudrate: Annotated[int, Field(gt=0)] = 115200
    rate_hz: Annotated[float, Field(ge=1, le=1000)] = 50.0
    replay: Path | None = None

    @model_validator(mode="after")
    def _one_source(self) -> InterferometerConfig:
        if (self.port is None) == (self.replay is None):
            raise ValueError("give exactly one of 'port' and 'replay'")
        return self


class _ControlledLinuxcnc(_Strict):
    """What both ways to a LinuxCNC share: the program xmalign runs, and its checks."""

    #: Where xmalign writes its program (a folder the LinuxCNC computer reads).
    program: Path
    joints: Annotated[int, Field(ge=1, le=9)] = 3
    #: Actual within this of commanded counts as standing still, mm.
    in_position_mm: Annotated[float, Field(gt=0, le=1)] = 0.002
    #: Largest distance from the plan's point at which a point is captured, mm.
    tolerance_mm: Annotated[float, Field(gt=0, le=1)] = 0.005
    #: xmalign may move the axes itself with MDI (``identify --live``); default: never.
    allow_mdi_moves: bool = False
    #: One reply (linuxcncrsh) or one command's acknowledgement (module), s
    #: (default: ``timeouts.io_s``).
    timeout_s: Seconds | None = None
    #: How long the program may take to show as running after the start, s.
    start_timeout_s: Seconds = START_TIMEOUT_S

    @property
    def cnc_program_path(self) -> str:
        """The program as LinuxCNC opens it (absolute: LinuxCNC starts from its INI's folder)."""
        return str(self.program.resolve())


class LinuxcncrshConfig(_ControlledLinuxcnc):
    """A LinuxCNC whose ``linuxcncrsh`` xmalign connects to (docs/hardware.md).

    Each password is given in the file or in an environment variable (``*_env``),
    or left at linuxcncrsh's default (``EMC``, ``EMCTOO``); linuxcncrsh takes one
    word of printable ASCII (it splits its requests on spaces).
    """

    host: str
    port: Annotated[int, Field(ge=1, le=65535)] = DEFAULT_PORT
    connect_password: Secret | None = None
    #: The name of an environment variable holding the connect password.
    connect_password_env: str | None = None
    enable_password: Secret | None = None
    #: The name of an environment variable holding the enable password.
    enable_password_env: str | None = None
    #: The same file as LinuxCNC opens it (default: ``program``).
    program_on_cnc: str | None = None

    @field_validator("connect_password", "enable_password")
    @classmethod
    def _one_word(cls, value: SecretStr | None, info: ValidationInfo) -> SecretStr | None:
        if value is not None:
            check_password(value.get_secret_value(), str(info.field_name).replace("_", " "))
        return value

    @model_validator(mode="after")
    def _password_or_env(self) -> LinuxcncrshConfig:
        for name in ("connect_password", "enable_password"):
            if getattr(self, name) is not None and getattr(self, f"{name}_env") is not None:
                raise ValueError(f"give '{name}' or '{name}_env', not both")
        return self

    @property
    def cnc_program_path(self) -> str:
        """The program as LinuxCNC opens it: ``program_on_cnc``, else ``program``'s
        absolute path."""
        return self.program_on_cnc or super().cnc_program_path

    def passwords(self) -> tuple[str, str]:
        """The connect and the enable password (from the file, the environment or
        linuxcncrsh's defaults); InputError naming the key when a variable is not set."""
        key = "machine_position.linuxcncrsh"
        connect = secret_value(
            self.connect_password, self.connect_password_env, f"{key}.connect_password_env"
        )
        enable = secret_value(
            self.enable_password, self.enable_password_env, f"{key}.enable_password_env"
        )
        return connect or DEFAULT_CONNECT_PASSWORD, enable or DEFAULT_ENABLE_PASSWORD


class LinuxcncModuleConfig(_ControlledLinuxcnc):
    """The LinuxCNC on this computer, through its Python module ``linuxcnc`` (docs/hardware.md)."""

    #: The folder holding LinuxCNC's ``linuxcnc`` module (default: the Python path, then
    #: Debian's /usr/lib/python3/dist-packages).
    module_dir: Path | None = None
    #: The NML configuration of the running LinuxCNC (default: the module's own,
    #: /usr/share/linuxcnc/linuxcnc.nml on Debian; an INI's [EMC] NML_FILE if it sets one).
    nml_file: Path | None = None


class MachinePositionConfig(_Strict):
    """``machine_position``: where the machine's position comes from, and who runs the
    program (the operator, or xmalign on a LinuxCNC); exactly the ``source``'s key is given."""

    source: Literal["prompt", "file", "linuxcncrsh", "linuxcnc", "mtconnect", "sinumerik"] = (
        "prompt"
    )
    file: Path | None = None
    linuxcncrsh: LinuxcncrshConfig | None = None
    linuxcnc: LinuxcncModuleConfig | None = None
    mtconnect: MTConnectConfig | None = None
    sinumerik: SinumerikConfig | None = None

    @model_validator(mode="after")
    def _source_given(self) -> MachinePositionConfig:
        for source in ("file", "linuxcncrsh", "linuxcnc", "mtconnect", "sinumerik"):
            if (self.source == source) != (getattr(self, source) is not None):
                raise ValueError(f"'{source}' is required with source: {source}, and only then")
        return self

    @property
    def follows_the_machine(self) -> bool:
        """The operator runs the program; xmalign follows the machine's position."""
        return self.source in ("file", "mtconnect", "sinumerik")

    @property
    def controlled(self) -> LinuxcncrshConfig | LinuxcncModuleConfig | None:
        """The LinuxCNC xmalign runs its program on (``linuxcncrsh`` or ``linuxcnc``)."""
        return self.linuxcncrsh or self.linuxcnc


class Timeouts(_Strict):
    """``timeouts``: the defaults of the waits, s (a controller's ``timeout_s`` overrides io_s)."""

    #: One request to a device.
    io_s: Annotated[float, Field(gt=0, le=600)] = 1.0
    #: One unit move.
    move_s: Annotated[float, Field(gt=0, le=3600)] = 30.0
    #: The machine reaching its next stop in a run on a controller (run or followed), s.
    machine_s: Annotated[float, Field(gt=0, le=86400)] = 600.0


class UnitsConfig(_Strict):
    """The whole ``units.yaml``."""

    format: str
    launch: UnitConfig
    receiver: UnitConfig
    interferometer: InterferometerConfig
    machine_position: MachinePositionConfig = MachinePositionConfig()
    timeouts: Timeouts = Timeouts()
    environment: EnvironmentConfig | None = None
    instruments: dict[str, str] = {}

    @model_validator(mode="after")
    def _one_node_per_id(self) -> UnitsConfig:
        """Two axes on one CAN bus with one node id would both answer every request."""
        owners: dict[tuple[str, str, int], str] = {}
        for kind in ("launch", "receiver"):
            unit = getattr(self, kind)
            if not isinstance(unit, CanopenUnitConfig):
                continue
            for node_id in unit_node_ids(kind, unit.node_ids):
                key = (unit.interface, unit.channel, node_id)
                if key in owners:
                    whose = "another axis" if owners[key] == kind else f"the {owners[key]} unit"
                    raise ValueError(
                        f"{kind}.node_ids: node {node_id} on {unit.channel} is already"
                        f" {whose}'s: give every axis its own node id"
                    )
                owners[key] = kind
        return self


def parse_units_config(data: object, source: str, base_dir: Path | None = None) -> UnitsConfig:
    """Validate a decoded ``units.yaml``; relative file paths are taken from ``base_dir``."""
    if not isinstance(data, dict):
        raise InputError(located(source, "top level", "expected a YAML mapping of keys"))
    check_format(data.get("format"), UNITS_FORMAT, source)
    config = validate(UnitsConfig, data, source)
    if base_dir is None:
        return config
    return config.model_copy(
        update={
            "interferometer": config.interferometer.model_copy(
                update={"replay": _resolve(config.interferometer.replay, base_dir)}
            ),
            "machine_position": _resolve_machine_position(config.machine_position, base_dir),
            "environment": resolve_environment(config.environment, base_dir),
        }
    )


def _resolve_machine_position(
    config: MachinePositionConfig, base_dir: Path
) -> MachinePositionConfig:
    rsh, local = config.linuxcncrsh, config.linuxcnc
    return config.model_copy(
        update={
            "file": _resolve(config.file, base_dir),
            "linuxcncrsh": None
            if rsh is None
            else rsh.model_copy(update={"program": base_dir / rsh.program}),
            "linuxcnc": None
            if local is None
            else local.model_copy(
                update={
                    "program": base_dir / local.program,
                    "module_dir": _resolve(local.module_dir, base_dir),
                    "nml_file": _resolve(local.nml_file, base_dir),
                }
            ),
            "sinumerik": resolve_paths(config.sinumerik, base_dir),
        }
    )


def _resolve(path: Path | None, base_dir: Path) -> Path | None:
    return None if path is None else base_dir / path


def load_units_config(path: str | Path) -> UnitsConfig:
    """Read and validate a ``units.yaml``; errors name the file and the key."""
    path = Path(path)
    return parse_units_config(read_yaml(path), str(path), path.parent)


@dataclass
class LiveDevices(ClosesOnExit):
    """The devices a ``units.yaml`` names, opened; :meth:`close` (or the end of a
    ``with`` block) releases them."""

    launch: PositioningUnit
    receiver: PositioningUnit
    interferometer: Interferometer
    mover: MachineMover
    closers: list[Callable[[], None]] = field(default_factory=list)
    environment: EnvironmentSource | None = None
    #: The controller xmalign runs the program on (``source: linuxcncrsh`` or ``linuxcnc``).
    controller: LinuxCncControl | None = None
    #: Where the machine's position is read (None: the operator types it).
    position: MachinePositionSource | None = None

    def close(self) -> None:
        """Close in reverse order of opening (heartbeats stop: the units then lock themselves)."""
        for close in reversed(self.closers):
            close()


def _open_unit(
    config: UnitConfig,
    kind: Literal["launch", "receiver"],
    timeouts: Timeouts,
    networks: dict[tuple[str, str], canopen.Network],
    closers: list[Callable[[], None]],
    clock: Clock | None = None,
) -> PositioningUnit:
    name = f"{kind} unit"
    if isinstance(config, CanopenUnitConfig):
        key = (config.interface, config.channel)
        if key not in networks:
            bus = open_can_bus(
                config.interface,
                config.channel,
                bitrate=config.bitrate,
                host=config.host,
                hop_limit=config.hop_limit,
            )
            network = canopen.Network(bus)
            network.connect()
            networks[key] = network
            closers.append(network.disconnect)
        unit = CanopenUnit(networks[key], kind, config.node_ids, f"{name} on {config.channel}")
        closers.append(unit.close)
        return unit
    if isinstance(config, ModbusTcpUnit):
        transport = tcp_transport(config.host, config.port, name, config.device_id, timeouts.io_s)
    else:
        transport = rtu_transport(
            config.serial_port, name, config.baudrate, config.device_id, timeouts.io_s
        )
    closers.append(transport.close)
    modbus_unit = ModbusUnit(transport, expected_kind=kind, clock=clock)
    modbus_unit.start_heartbeat()
    closers.append(modbus_unit.stop_heartbeat)
    return modbus_unit


def _open_interferometer(
    config: InterferometerConfig,
    timeouts: Timeouts,
    closers: list[Callable[[], None]],
    clock: Clock | None,
) -> Interferometer:
    if config.replay is not None:
        return ReplayInterferometer(config.replay)
    connection = open_serial(str(config.port), config.baudrate, timeouts.io_s)
    closers.append(connection.close)
    name = f"interferometer on {config.port}"
    interferometer = SerialInterferometer(connection, name, clock)
    interferometer.set_rate(config.rate_hz)
    return interferometer


def open_devices(
    config: UnitsConfig,
    machine: Machine,
    ask: Callable[[str], str] = input,
    tell: Callable[[str], None] = print,
    clock: Clock | None = None,
) -> LiveDevices:
    """Open both units, the interferometer and the machine-position source of ``config``.

    Anything opened before a failure is closed again before the error propagates.
    ``clock`` is what the Modbus units and the controller wait on and what the
    interferometer tells before each wait for a streamed sample (default the wall clock;
    the simulator's shared virtual clock when it serves the devices in-process).
    """
    closers: list[Callable[[], None]] = []
    networks: dict[tuple[str, str], canopen.Network] = {}
    try:
        launch = _open_unit(config.launch, "launch", config.timeouts, networks, closers, clock)
        receiver = _open_unit(
            config.receiver, "receiver", config.timeouts, networks, closers, clock
        )
        interferometer = _open_interferometer(
            config.interferometer, config.timeouts, closers, clock
        )
        environment = (
            None
            if config.environment is None
            else open_environment(config.environment, config.timeouts.io_s, closers)
        )
        controller = _open_controller(config, closers, clock)
        position = controller or _position_source(config, closers)
    except BaseException:
        for close in reversed(closers):
            close()
        raise
    mover = _mover(config, machine, controller, ask, tell, position)
    return LiveDevices(
        launch, receiver, interferometer, mover, closers, environment, controller, position
    )


def _mover(
    config: UnitsConfig,
    machine: Machine,
    controller: LinuxCncControl | None,
    ask: Callable[[str], str],
    tell: Callable[[str], None],
    position: MachinePositionSource | None,
) -> MachineMover:
    """Who moves the machine: xmalign over MDI where ``units.yaml`` allows it, otherwise
    the operator (asked to; the position read from ``position`` where there is one)."""
    controlled = config.machine_position.controlled
    if controller is not None and controlled is not None and controlled.allow_mdi_moves:
        return MdiMover(controller, machine, controlled.tolerance_mm, config.timeouts.machine_s)
    return OperatorPrompt(machine, ask, tell, position)


def _position_source(
    config: UnitsConfig, closers: list[Callable[[], None]]
) -> MachinePositionSource | None:
    """Where an operator-run machine's position is read: a file, or a controller followed."""
    source = config.machine_position
    if source.file is not None:
        return FilePositions(source.file)
    if source.mtconnect is not None:
        return open_mtconnect_source(source.mtconnect, config.timeouts.io_s, closers)
    if source.sinumerik is not None:
        return open_sinumerik_source(source.sinumerik, config.timeouts.io_s, closers)
    return None


def _open_controller(
    config: UnitsConfig, closers: list[Callable[[], None]], clock: Clock | None
) -> LinuxCncControl | None:
    """The LinuxCNC of ``source: linuxcncrsh`` (connected and enabled for control) or of
    ``source: linuxcnc`` (through its module on this computer)."""
    source = config.machine_position
    cnc: LinuxCncControl
    if source.linuxcncrsh is not None:
        rsh = source.linuxcncrsh
        connect_password, enable_password = rsh.passwords()
        cnc = open_linuxcnc(
            rsh.host,
            rsh.port,
            rsh.timeout_s or config.timeouts.io_s,
            connect_password,
            enable_password,
            rsh.joints,
            rsh.in_position_mm,
            clock,
            rsh.start_timeout_s,
        )
    elif source.linuxcnc is not None:
        local = source.linuxcnc
        cnc = open_local_linuxcnc(
            local.module_dir,
            local.nml_file,
            local.joints,
            local.in_position_mm,
            clock,
            local.timeout_s or config.timeouts.io_s,
            local.start_timeout_s,
        )
    else:
        return None
    closers.append(cnc.close)
    return cnc
