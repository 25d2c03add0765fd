"""A virtual world served over the real protocols to a host in the same process.

:func:`serve_world` starts, on 127.0.0.1 and new ptys, what ``xmalign sim
serve`` serves to another process: both positioning units as Modbus TCP
servers (ephemeral ports), the interferometer's line protocol on a pty, and the
CNC: a simulated LinuxCNC over linuxcncrsh that runs the program the host
starts (:func:`serve_world_with_linuxcnc`, the dry run), or a CNC running a
given G-code program that keeps a position file up to date (:func:`serve_world`,
``run --sim``). It writes the ``units.yaml`` a technician would write for
them, so the host opens them with :func:`firmware_iface.config.open_devices`
exactly as in a live run.

Host and servers share one :class:`~sim.clock.LockstepClock` (the world's):
virtual time advances only when the host sleeps or the interferometer streams
a sample the host waits for; the CNC runs its program as a follower of that
clock, the units' watchdogs and the host's heartbeat count in it. A
ten-minute measuring program therefore takes seconds, and the host reads what
the same world in-process would give (docs/simulator.md).
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from firmware_iface.config import UnitsConfig, load_units_config
from sim.clock import LockstepClock
from sim.cnc import SimulatedCnc
from sim.servers.linuxcncrsh import LinuxcncrshServer
from sim.servers.modbus import ModbusUnitServer
from sim.servers.serial_pty import PtyInterferometerServer
from sim.servers.served_cnc import PROGRAM_END, WAITING, ServedCnc
from sim.world import World
from xmalign.calibration import PRESS_CYCLE_START
from xmalign.errors import DeviceError, DeviceTimeoutError
from xmalign.geometry import Vec
from xmalign.machine import Machine

#: Where every served device listens.
LOOPBACK = "127.0.0.1"
#: How long the simulated operator lets the CNC reach a programmed stop, virtual s.
REACH_STOP_S = 600.0
#: How long the host waits for one reply of a served device, wall-clock s (``units.yaml``
#: ``timeouts.io_s``). In lockstep a server answers at the present virtual time whenever
#: its thread gets the CPU, and virtual time does not pass meanwhile; with the default 1 s
#: a computer busy for a second made the host take a late reply for a lost one: a Modbus
#: request sent again (the alignment, then every reading, differed between two runs of one
#: seed) or a serial or linuxcncrsh read that failed the run. A dead server still ends it.
LOCKSTEP_IO_S = 60.0


def served_cnc(
    world: World,
    machine: Machine,
    program: str,
    dialect: str,
    position_file: Path,
    tell: Callable[[str], None],
    cnc: SimulatedCnc | None = None,
) -> ServedCnc:
    """The world's machine moved by a CNC running ``program`` (checked here, InputError).

    ``cnc`` (default: a new one, which the interferometer then follows) is the
    CNC of the world; on a :class:`LockstepClock` the program follows its time.
    """
    if cnc is None:
        cnc = SimulatedCnc(machine, world.clock)
        world.interferometer.position = cnc
    lockstep = world.clock if isinstance(world.clock, LockstepClock) else None
    return ServedCnc(
        cnc, machine, world.clock, program, dialect, position_file, tell, lockstep=lockstep
    )


def units_yaml(
    launch_port: int, receiver_port: int, interferometer_port: str, machine_position: str
) -> str:
    """The ``units.yaml`` of the served devices (docs/hardware.md); ``machine_position``
    is its ``machine_position`` block in flow style. Replies are waited for
    :data:`LOCKSTEP_IO_S` (wall clock)."""
    return (
        "format: xmalign.units/1\n"
        f"launch: {{transport: modbus-tcp, host: {LOOPBACK}, port: {launch_port}}}\n"
        f"receiver: {{transport: modbus-tcp, host: {LOOPBACK}, port: {receiver_port}}}\n"
        f"interferometer: {{port: {interferometer_port}, rate_hz: 50}}\n"
        f"machine_position: {machine_position}\n"
        f"timeouts: {{io_s: {LOCKSTEP_IO_S:g}}}\n"
    )


@dataclass
class ServedWorld:
    """The served devices of a world, its ``units.yaml`` and the CNC's operator."""

    clock: LockstepClock
    cnc: ServedCnc
    config_path: Path
    config: UnitsConfig
    #: What the CNC said, in order (``sim serve`` prints the same).
    cnc_messages: list[str] = field(default_factory=list)

    def run_to_stop_at(self, position_mm: Vec, tolerance_mm: float = 0.005) -> None:
        """The operator presses cycle start until the CNC waits at ``position_mm`` (3,).

        As a technician brings the program to the line a run starts with (a
        resumed run skips the lines it has); DeviceError when the program
        ends twice without stopping there.
        """
        ends = 0
        while True:
            self.press_cycle_start()
            self._wait_for_stop()
            miss = float(np.linalg.norm(self.cnc.cnc.position_mm() - position_mm))
            if miss <= tolerance_mm:
                return
            ends += self.cnc_messages.count(PROGRAM_END)
            self.cnc_messages.clear()
            if ends >= 2:
                raise DeviceError(
                    f"the served CNC's program never stops at {np.round(position_mm, 3).tolist()}"
                    " mm: program and plan do not match"
                )

    def _wait_for_stop(self) -> None:
        deadline_s = self.clock.now() + REACH_STOP_S
        while not self.cnc_messages or self.cnc_messages[-1] != WAITING:
            if self.clock.now() >= deadline_s:
                raise DeviceTimeoutError(
                    f"the served CNC did not reach a programmed stop in {REACH_STOP_S:.0f} s"
                )
            self.clock.sleep(0.1)

    def press_cycle_start(self) -> None:
        self.cnc.cycle_start()

    def operator(self, message: str) -> None:
        """The technician told by the run: presses cycle start once the units are set (the
        program is brought to the first line's stop beforehand, :meth:`run_to_stop_at`)."""
        if message.endswith(PRESS_CYCLE_START):
            self.press_cycle_start()


@dataclass
class ServedController:
    """The served devices of a world whose CNC is a simulated LinuxCNC (linuxcncrsh)."""

    clock: LockstepClock
    server: LinuxcncrshServer
    config_path: Path
    config: UnitsConfig


@contextmanager
def serve_world(
    world: World, machine: Machine, program: str, dialect: str, cnc: SimulatedCnc | None = None
) -> Iterator[ServedWorld]:
    """Serve ``world`` (on a :class:`LockstepClock`) with a CNC running ``program``.

    Everything is stopped again on exit; the ``units.yaml`` and the position
    file live in a temporary folder until then.
    """
    with ExitStack() as stack:
        clock, folder, ports = _serve_devices(world, stack)
        messages: list[str] = []
        position_file = folder / "position.txt"
        cnc_server = served_cnc(
            world, machine, program, dialect, position_file, messages.append, cnc
        )
        cnc_server.start()
        stack.callback(cnc_server.stop)
        config_path = folder / "units.yaml"
        source = f"{{source: file, file: {position_file}}}"
        config_path.write_text(units_yaml(*ports, source), encoding="utf-8")
        yield ServedWorld(clock, cnc_server, config_path, load_units_config(config_path), messages)


@contextmanager
def serve_world_with_linuxcnc(
    world: World, machine: Machine, cnc: SimulatedCnc
) -> Iterator[ServedController]:
    """Serve ``world`` (on a :class:`LockstepClock`) with ``cnc`` as a LinuxCNC: linuxcncrsh.

    The simulated LinuxCNC follows the world's clock: a program the host
    opens and runs over linuxcncrsh moves ``cnc`` in virtual time, and a hold,
    resume or abort acts at the virtual time it arrives. The ``units.yaml``
    (``source: linuxcncrsh``) names a program file in the temporary folder,
    which the host writes as it does for a real LinuxCNC.
    """
    with ExitStack() as stack:
        clock, folder, ports = _serve_devices(world, stack)
        server = LinuxcncrshServer(cnc, machine, LOOPBACK, 0, lockstep=clock)
        server.start()
        stack.callback(server.stop)
        config_path = folder / "units.yaml"
        program = folder / "xmalign-run.ngc"
        source = (
            f"{{source: linuxcncrsh, linuxcncrsh: {{host: {LOOPBACK}, port: {server.port},"
            f" program: {program}}}}}"
        )
        config_path.write_text(units_yaml(*ports, source), encoding="utf-8")
        yield ServedController(clock, server, config_path, load_units_config(config_path))


def _serve_devices(
    world: World, stack: ExitStack
) -> tuple[LockstepClock, Path, tuple[int, int, str]]:
    """Both units on Modbus TCP and the interferometer on a pty, stopped when ``stack``
    closes; the world's clock, a temporary folder and (launch port, receiver port, pty)."""
    if not isinstance(world.clock, LockstepClock):
        raise TypeError("serving a world in-process needs a world built on a LockstepClock")
    clock = world.clock
    folder = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="xmalign-served-")))
    servers = [ModbusUnitServer(unit, LOOPBACK, 0) for unit in (world.launch, world.receiver)]
    for server in servers:
        server.start()
        stack.callback(server.stop)
    pty = PtyInterferometerServer(world.interferometer, lockstep=clock)
    pty.start()
    stack.callback(pty.stop)
    return clock, folder, (servers[0].port, servers[1].port, pty.port)
