"""``xmalign sim``: serve the simulated devices over the real protocols."""

from __future__ import annotations

import math
import signal
import threading
from contextlib import ExitStack
from pathlib import Path
from typing import Annotated, Literal

import typer

from xmalign.cli.common import (
    LogFileOption,
    check_seed,
    console,
    machine_or_default,
    start_log_file,
    stop_log_file,
)
from xmalign.errors import InputError

sim_app = typer.Typer(help="The simulator: virtual machine, positioning units, interferometer.")


def _host_port(text: str, default_host: str) -> tuple[str, int]:
    """``PORT`` or ``HOST:PORT`` (the host defaults to ``--host``)."""
    host, _, port = text.rpartition(":")
    if not port.isdigit() or not 0 <= int(port) <= 65535 or (":" in text and not host):
        raise InputError(f"--modbus '{text}': expected PORT or HOST:PORT, e.g. 5020")
    return host or default_host, int(port)


@sim_app.command()
def serve(
    unit: Annotated[
        str, typer.Option(help="Which unit to serve over Modbus: launch or receiver.")
    ] = "launch",
    modbus: Annotated[
        str | None,
        typer.Option(help="Serve the unit over Modbus TCP on PORT (on --host) or HOST:PORT."),
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
            help="Serve every axis of both units as CiA 402 nodes on this python-can "
            "channel (a multicast group for udp_multicast, a name for virtual)."
        ),
    ] = None,
    can_interface: Annotated[
        str, typer.Option(help="python-can interface of --canopen.")
    ] = "udp_multicast",
    can_hop_limit: Annotated[
        int,
        typer.Option(help="udp_multicast TTL / hop limit; 0 keeps the bus on this computer."),
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
) -> None:
    """Serve the simulated devices until interrupted (Ctrl-C stops cleanly)."""
    # imported here: the simulator is only loaded when serving
    from sim.world import build_world

    if unit not in ("launch", "receiver"):
        raise InputError(f"--unit '{unit}': expected launch or receiver")
    nothing = modbus is None and not rtu and canopen is None
    if nothing and not interferometer_pty and not station_pty:
        raise InputError(
            "nothing to serve: give --modbus, --rtu, --canopen, --interferometer-pty"
            " and/or --station-pty"
        )
    check_seed(seed)
    if can_hop_limit < 0:
        raise InputError(f"--can-hop-limit {can_hop_limit}: expected 0 or more")
    address = _host_port(modbus, host) if modbus is not None else None
    kind: Literal["launch", "receiver"] = "launch" if unit == "launch" else "receiver"
    log_handler = start_log_file(log_file)
    world = build_world(
        machine_or_default(machine), seed=seed, real_time=True, gamma_rad=math.radians(gamma_deg)
    )
    stopped = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stopped.set())
    signal.signal(signal.SIGTERM, lambda *_: stopped.set())
    with ExitStack() as servers:
        servers.callback(stop_log_file, log_handler)
        from sim.servers.modbus import ControllingHost

        controlling_host = ControllingHost()  # one per unit, whichever server it writes on
        if address is not None:
            from sim.servers.modbus import ModbusUnitServer

            server = ModbusUnitServer(getattr(world, kind), *address, device_id, controlling_host)
            server.start()
            servers.callback(server.stop)
            console.print(f"modbus {kind} unit on {server.where} (device id {device_id})")
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
                [world.launch, world.receiver], canopen, can_interface, hop_limit=can_hop_limit
            )
            nodes.start()
            servers.callback(nodes.stop)
            console.print(
                f"canopen nodes {nodes.node_ids} on {can_interface} channel {canopen}",
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
        console.print("serving; Ctrl-C to stop", highlight=False)
        while not stopped.wait(0.2):
            pass
    console.print("stopped")


def register(app: typer.Typer) -> None:
    app.add_typer(sim_app, name="sim")
