"""``xmalign sim``: serve the simulated devices over the real protocols."""

from __future__ import annotations

import math
import signal
import threading
from contextlib import ExitStack
from pathlib import Path
from typing import Annotated, Literal

import typer

from xmalign.cli.common import console, machine_or_default
from xmalign.errors import InputError

sim_app = typer.Typer(help="The simulator: virtual machine, positioning units, interferometer.")


def _host_port(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    if not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise InputError(f"--modbus '{text}': expected HOST:PORT, e.g. 127.0.0.1:5020")
    return host, int(port)


@sim_app.command()
def serve(
    unit: Annotated[
        str, typer.Option(help="Which unit to serve over Modbus: launch or receiver.")
    ] = "launch",
    modbus: Annotated[
        str | None, typer.Option(help="Serve the unit over Modbus TCP on HOST:PORT.")
    ] = None,
    canopen: Annotated[
        str | None,
        typer.Option(
            help="Serve every axis of both units as CiA 402 nodes on this "
            "python-can channel (interface udp_multicast)."
        ),
    ] = None,
    interferometer_pty: Annotated[
        bool, typer.Option(help="Serve the interferometer on a new pty (path printed).")
    ] = False,
    machine: Annotated[Path | None, typer.Option(help="Machine YAML (default: reference).")] = None,
    seed: Annotated[int, typer.Option(help="Seed of the virtual setup.")] = 0,
    device_id: Annotated[int, typer.Option(help="Modbus unit id.")] = 1,
    gamma_deg: Annotated[float, typer.Option(help="True launch-unit azimuth, deg.")] = 0.0,
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
    if modbus is None and canopen is None and not interferometer_pty and not station_pty:
        raise InputError(
            "nothing to serve: give --modbus, --canopen, --interferometer-pty and/or --station-pty"
        )
    kind: Literal["launch", "receiver"] = "launch" if unit == "launch" else "receiver"
    world = build_world(
        machine_or_default(machine), seed=seed, real_time=True, gamma_rad=math.radians(gamma_deg)
    )
    stopped = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stopped.set())
    signal.signal(signal.SIGTERM, lambda *_: stopped.set())
    with ExitStack() as servers:
        if modbus is not None:
            from sim.servers.modbus import ModbusUnitServer

            host, port = _host_port(modbus)
            server = ModbusUnitServer(getattr(world, kind), host, port, device_id)
            server.start()
            servers.callback(server.stop)
            console.print(f"modbus {kind} unit on {host}:{port} (device id {device_id})")
        if canopen is not None:
            from sim.servers.canopen_node import CanopenUnitServer

            nodes = CanopenUnitServer([world.launch, world.receiver], canopen, "udp_multicast")
            nodes.start()
            servers.callback(nodes.stop)
            console.print(f"canopen nodes {nodes.node_ids} on udp_multicast channel {canopen}")
        if interferometer_pty:
            from sim.servers.serial_pty import PtyInterferometerServer

            pty = PtyInterferometerServer(world.interferometer)
            pty.start()
            servers.callback(pty.stop)
            console.print(f"interferometer on {pty.port}")
        if station_pty:
            from sim.environment import serve_station

            port = serve_station(world, servers)
            console.print(f"weather station on {port}")
        console.print("serving; Ctrl-C to stop", highlight=False)
        while not stopped.wait(0.2):
            pass
    console.print("stopped")


def register(app: typer.Typer) -> None:
    app.add_typer(sim_app, name="sim")
