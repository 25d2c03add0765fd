"""``xmalign sim``: serve the simulated devices over the real protocols."""

from __future__ import annotations

import logging
import math
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

import typer

from xmalign.cli.common import (
    LogFileOption,
    check_seed,
    console,
    machine_or_default,
    start_log_file,
    stop_log_file,
)
from xmalign.errors import DeviceError, InputError
from xmalign.formats.common import located, read_text, refuse_overwriting
from xmalign.machine import Machine

if TYPE_CHECKING:
    from sim.servers.served_cnc import ServedCnc
    from sim.world import World

log = logging.getLogger(__name__)
sim_app = typer.Typer(help="The simulator: virtual machine, positioning units, interferometer.")


def _host_port(text: str, default_host: str) -> tuple[str, int]:
    """``PORT`` or ``HOST:PORT`` (the host defaults to ``--host``)."""
    host, _, port = text.rpartition(":")
    if not port.isdigit() or not 0 <= int(port) <= 65535 or (":" in text and not host):
        raise InputError(f"--modbus '{text}': expected PORT or HOST:PORT, e.g. 5020")
    return host or default_host, int(port)


def _check_position_file(path: Path, option: str = "--position-file") -> None:
    """An existing position file (``option``) must be one: anything else would be
    overwritten."""
    if not path.is_file() or path.stat().st_size == 0:
        return
    from firmware_iface.machine_position import parse_position

    first = read_text(path).partition("\n")[0]
    if parse_position(first) is None:
        raise InputError(
            located(
                path,
                option,
                "holds something other than a machine position ('x y z'); the simulated"
                " CNC would overwrite it: give a new file name",
            )
        )


def _check_can_options(channel: str, interface: str, hop_limit: int) -> None:
    from firmware_iface.can_bus import UDP_LOCAL, check_interface, multicast_group

    try:
        check_interface(interface)
    except ValueError as error:
        raise InputError(f"--can-interface {interface}: {error}") from error
    if interface == UDP_LOCAL:
        try:
            multicast_group(channel)
        except ValueError as error:
            raise InputError(f"--canopen {channel}: {error}") from error
    if not 0 <= hop_limit <= 255:
        raise InputError(f"--can-hop-limit {hop_limit}: expected 0 to 255")


@sim_app.command()
def serve(
    unit: Annotated[
        str, typer.Option(help="Which unit to serve over Modbus: launch or receiver.")
    ] = "launch",
    modbus: Annotated[
        str | None,
        typer.Option(help="Serve the unit over Modbus TCP on PORT (on --host) or HOST:PORT."),
    ] = None,
    modbus_receiver: Annotated[
        str | None,
        typer.Option(
            help="Also serve the receiver unit of the same world over Modbus TCP on PORT or"
            " HOST:PORT (--unit is then the launch unit)."
        ),
    ] = None,
    rtu: Annotated[
        bool, typer.Option("--rtu", help="Serve the unit over Modbus RTU on a new pty.")
    ] = False,
    host: Annotated[
        str, typer.Option(help="Interface the Modbus TCP server binds to.")
    ] = "127.0.0.1",
    canopen: Annotated[
        str | None,
        typer.Option(
            help="Serve every axis of both units as CiA 402 nodes on this CAN channel (an"
            " IPv4 multicast group such as 239.74.163.2 for udp_local)."
        ),
    ] = None,
    can_interface: Annotated[
        str,
        typer.Option(
            help="CAN interface of --canopen: udp_local (the simulated bus between processes)"
            " or a python-can interface (socketcan, virtual, ...)."
        ),
    ] = "udp_local",
    can_host: Annotated[
        str,
        typer.Option(help="udp_local: address of the network interface the bus runs on."),
    ] = "127.0.0.1",
    can_hop_limit: Annotated[
        int,
        typer.Option(help="udp_local TTL / hop limit; 0 keeps the bus on this computer."),
    ] = 0,
    interferometer_pty: Annotated[
        bool, typer.Option(help="Serve the interferometer on a new pty (path printed).")
    ] = False,
    machine: Annotated[Path | None, typer.Option(help="Machine YAML (default: reference).")] = None,
    seed: Annotated[int, typer.Option(help="Seed of the virtual setup.")] = 0,
    device_id: Annotated[int, typer.Option(help="Modbus unit id.")] = 1,
    gamma_deg: Annotated[float, typer.Option(help="True launch-unit azimuth, deg.")] = 0.0,
    log_file: LogFileOption = None,
    station_pty: Annotated[
        bool,
        typer.Option(help="Serve a weather station (drifting 22-25 °C shop) on a new pty."),
    ] = False,
    position_file: Annotated[
        Path | None,
        typer.Option(
            help="Run a simulated CNC that writes its tool point to this file (units.yaml"
            " machine_position source: file); needs --program."
        ),
    ] = None,
    program: Annotated[
        Path | None,
        typer.Option(
            help="The G-code the CNC of --position-file runs: Enter on standard input is"
            " cycle start (starts it, goes on after each M0, starts it again after its end)."
        ),
    ] = None,
    dialect: Annotated[
        str | None, typer.Option(help="G-code dialect of --program (default: controller's).")
    ] = None,
    linuxcncrsh: Annotated[
        str | None,
        typer.Option(
            help="Serve a simulated CNC as LinuxCNC's remote shell linuxcncrsh on PORT (or"
            " HOST:PORT): units.yaml machine_position source: linuxcncrsh runs its program."
        ),
    ] = None,
    follow_position_file: Annotated[
        Path | None,
        typer.Option(
            help="A file another CNC keeps its tool point in (last line 'x y z', mm; e.g. a"
            " real LinuxCNC's actual position): the virtual machine carries the receiver"
            " there. A line 'block-beam SECONDS' on standard input then interrupts the beam."
        ),
    ] = None,
) -> None:
    """Serve the simulated devices until interrupted (Ctrl-C stops cleanly)."""
    # imported here: the simulator is only loaded when serving
    from sim.world import build_world

    if unit not in ("launch", "receiver"):
        raise InputError(f"--unit '{unit}': expected launch or receiver")
    if modbus_receiver is not None and unit != "launch":
        raise InputError("--modbus-receiver serves the receiver: --unit must be launch")
    if (position_file is None) != (program is None):
        raise InputError("--position-file and --program go together")
    cncs = [follow_position_file, position_file, linuxcncrsh]
    if sum(option is not None for option in cncs) > 1:
        raise InputError(
            "give one of --position-file, --follow-position-file and --linuxcncrsh:"
            " the machine has one CNC"
        )
    nothing = modbus is None and modbus_receiver is None and not rtu and canopen is None
    if nothing and not interferometer_pty and not station_pty and position_file is None:
        raise InputError(
            "nothing to serve: give --modbus, --modbus-receiver, --rtu, --canopen,"
            " --interferometer-pty, --station-pty and/or --position-file"
        )
    check_seed(seed)
    refuse_overwriting(
        {"--machine": machine, "--program": program},
        {"--position-file": position_file},
        {"--log-file": log_file},
    )
    if position_file is not None:
        _check_position_file(position_file)
    if canopen is not None:
        _check_can_options(canopen, can_interface, can_hop_limit)
    address = _host_port(modbus, host) if modbus is not None else None
    receiver_address = _host_port(modbus_receiver, host) if modbus_receiver is not None else None
    kind: Literal["launch", "receiver"] = "launch" if unit == "launch" else "receiver"
    log_handler = start_log_file(log_file)
    machine_model = machine_or_default(machine)
    world = build_world(machine_model, seed=seed, real_time=True, gamma_rad=math.radians(gamma_deg))
    served_cnc = (
        _served_cnc(world, machine_model, position_file, program, dialect)
        if position_file is not None and program is not None
        else None
    )
    stopped = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stopped.set())
    signal.signal(signal.SIGTERM, lambda *_: stopped.set())
    with ExitStack() as servers:
        servers.callback(stop_log_file, log_handler)
        died = servers.enter_context(stop_when_a_thread_dies(stopped))
        from sim.servers.modbus import ControllingHost

        controlling_host = ControllingHost()  # one per unit, whichever server it writes on
        if address is not None:
            from sim.servers.modbus import ModbusUnitServer

            server = ModbusUnitServer(getattr(world, kind), *address, device_id, controlling_host)
            server.start()
            servers.callback(server.stop)
            console.print(f"modbus {kind} unit on {server.where} (device id {device_id})")
        if receiver_address is not None:
            from sim.servers.modbus import ModbusUnitServer

            receiver_server = ModbusUnitServer(world.receiver, *receiver_address, device_id)
            receiver_server.start()
            servers.callback(receiver_server.stop)
            console.print(
                f"modbus receiver unit on {receiver_server.where} (device id {device_id})"
            )
        if rtu:
            from sim.servers.modbus import ModbusRtuUnitServer

            rtu_server = ModbusRtuUnitServer(
                getattr(world, kind), device_id, controlling_host=controlling_host
            )
            rtu_server.start()
            servers.callback(rtu_server.stop)
            console.print(
                f"modbus-rtu {kind} unit on {rtu_server.serial_port} (device id {device_id})",
                highlight=False,
            )
        if canopen is not None:
            from sim.servers.canopen_node import CanopenUnitServer

            nodes = CanopenUnitServer(
                [world.launch, world.receiver],
                canopen,
                can_interface,
                hop_limit=can_hop_limit,
                host=can_host,
            )
            servers.callback(nodes.stop)
            nodes.start()
            console.print(
                f"canopen nodes {nodes.node_ids} on {nodes.bus_info}",
                highlight=False,
            )
        if interferometer_pty:
            from sim.servers.serial_pty import PtyInterferometerServer

            pty = PtyInterferometerServer(world.interferometer)
            pty.start()
            servers.callback(pty.stop)
            console.print(f"interferometer on {pty.port}", highlight=False)
        if station_pty:
            from sim.environment import serve_station

            port = serve_station(world, servers)
            console.print(f"weather station on {port}", highlight=False)
        if linuxcncrsh is not None:
            where = _serve_linuxcncrsh(world, machine_model, _host_port(linuxcncrsh, host), servers)
            console.print(f"linuxcncrsh on {where}", highlight=False)
        if follow_position_file is not None:
            _follow_position_file(world, follow_position_file, servers)
            console.print(f"machine follows {follow_position_file}", highlight=False)
        if served_cnc is not None:
            served_cnc.start()
            servers.callback(served_cnc.stop)
            console.print(f"cnc position in {position_file}", highlight=False)
            _press_cycle_start_on_enter(served_cnc)
        console.print("serving; Ctrl-C to stop", highlight=False)
        while not stopped.wait(0.2):
            pass
    if died:
        raise DeviceError(f"sim serve stopped: {died[0]}")
    console.print("stopped")


@contextmanager
def stop_when_a_thread_dies(stopped: threading.Event) -> Iterator[list[str]]:
    """While inside, an exception that ends any thread (a server's) sets ``stopped``.

    Yields the list of what ended them (thread name and error), so that ``serve``
    stops with one line instead of saying "serving" with a device gone. The
    traceback goes to the log.
    """
    died: list[str] = []
    previous = threading.excepthook

    def thread_died(args: threading.ExceptHookArgs) -> None:
        name = args.thread.name if args.thread is not None else "a thread"
        died.append(f"{name}: {args.exc_type.__name__}: {args.exc_value}")
        log.error("sim serve: thread %s died", name, exc_info=args.exc_value)
        stopped.set()

    threading.excepthook = thread_died
    try:
        yield died
    finally:
        threading.excepthook = previous


def _served_cnc(
    world: World, machine: Machine, position_file: Path, program: Path, dialect: str | None
) -> ServedCnc:
    """The world's machine moved by a simulated CNC running ``program`` (checked here)."""
    from sim.servers.served_world import served_cnc
    from trajectories.gcode import resolve_dialect
    from xmalign.cli.run import read_text

    def tell(message: str) -> None:
        console.print(message, markup=False, highlight=False)

    return served_cnc(
        world,
        machine,
        read_text(program, "G-code program"),
        resolve_dialect(machine, dialect),
        position_file,
        tell,
    )


def _serve_linuxcncrsh(
    world: World, machine: Machine, address: tuple[str, int], servers: ExitStack
) -> str:
    """A simulated CNC moving the world's machine, commanded over linuxcncrsh's protocol."""
    from sim.cnc import SimulatedCnc
    from sim.servers.linuxcncrsh import LinuxcncrshServer

    cnc = SimulatedCnc(machine, world.clock)
    world.interferometer.position = cnc
    server = LinuxcncrshServer(cnc, machine, *address)
    server.start()
    servers.callback(server.stop)
    return server.where


def _follow_position_file(world: World, path: Path, servers: ExitStack) -> None:
    """The world's receiver carried where the file says the CNC stands; 'block-beam S'
    lines on standard input interrupt the beam for S seconds."""
    from firmware_iface.machine_position import FilePositions
    from sim.servers.followed_machine import FollowedMachine

    followed = FollowedMachine(FilePositions(path))
    world.interferometer.position = followed
    followed.start()
    servers.callback(followed.stop)

    def read() -> None:
        for line in sys.stdin:
            words = line.split()
            if len(words) == 2 and words[0] == "block-beam":
                world.interferometer.interrupt(float(words[1]))
                console.print(f"beam blocked for {words[1]} s", highlight=False)

    threading.Thread(target=read, name="beam-commands", daemon=True).start()


def _press_cycle_start_on_enter(served_cnc: ServedCnc) -> None:
    """Every line on standard input is a press of cycle start (until end of input)."""

    def read() -> None:
        for _ in sys.stdin:
            served_cnc.cycle_start()

    threading.Thread(target=read, name="cycle-start", daemon=True).start()


@sim_app.command("publish-position")
def publish_position(
    file: Annotated[Path, typer.Argument(help="The position file to keep up to date.")],
    module_dir: Annotated[
        Path | None,
        typer.Option(help="Where LinuxCNC's Python module is (default: Debian's place)."),
    ] = None,
    nml_file: Annotated[
        Path | None, typer.Option(help="LinuxCNC's NML file, only if its INI sets one.")
    ] = None,
    period_ms: Annotated[
        float, typer.Option(min=1.0, max=1000.0, help="How often the position is read, ms.")
    ] = 5.0,
) -> None:
    """Publish a LinuxCNC's actual position (machine coordinates, mm) to FILE for
    'sim serve --follow-position-file'; ends by itself when LinuxCNC stops."""
    from firmware_iface.linuxcnc_module import open_local_linuxcnc
    from sim.position_publisher import publish_positions

    refuse_overwriting({"--nml-file": nml_file}, {"FILE": file})
    _check_position_file(file, "FILE")
    cnc = open_local_linuxcnc(module_dir, nml_file)
    stopped = threading.Event()
    for number in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(number, lambda *_: stopped.set())
    console.print(f"publishing the position of {cnc.name} to {file}", highlight=False)
    try:
        reason = publish_positions(cnc, file, stopped, period_ms / 1000.0)
    except KeyboardInterrupt:
        reason = "interrupted"
    console.print(f"publishing ended: {reason}", highlight=False, markup=False)


def register(app: typer.Typer) -> None:
    app.add_typer(sim_app, name="sim")
