"""Role interfaces (``typing.Protocol``) that drivers and the simulator implement.

The core and the orchestration code only ever talk to these roles, so a real
unit on Modbus, a CiA 402 node and a simulated unit are interchangeable. All
angles are radians, lengths mm, times seconds. Methods that wait take a
timeout and raise :class:`xmalign.errors.DeviceTimeoutError` when it runs out.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, Protocol, Self, runtime_checkable

import numpy as np

from xmalign.errors import InputError
from xmalign.geometry import Vec

CHANNELS = (
    "linear_um",
    "straightness_v_um",
    "straightness_w_um",
    "angle_u_urad",
    "angle_v_urad",
    "angle_w_urad",
)


@dataclass(frozen=True)
class InterferometerReading:
    """One six-channel reading at the receiver cp, in the line frame (docs/conventions.md).

    ``channels`` holds the six values in the order of :data:`CHANNELS`
    (um and urad); ``beam_ok`` is False when any channel is out of range.
    ``signal_pct`` is the receiver's signal strength (0 to 100 %), where the
    instrument reports it: above 0 the beam enters the receiver, whether or not
    the channels are in range (None: not reported; ``beam_ok`` stands for it).
    """

    time_s: float
    channels: Vec
    beam_ok: bool = True
    signal_pct: float | None = None

    def sees_beam(self, min_signal_pct: float) -> bool:
        """Whether the receiver sees the beam at all (signal at least ``min_signal_pct``)."""
        if self.signal_pct is None:
            return self.beam_ok
        return self.beam_ok or self.signal_pct >= min_signal_pct

    def channel(self, name: str) -> float:
        return float(self.channels[CHANNELS.index(name)])


@runtime_checkable
class Clock(Protocol):
    """Time source: wall time for hardware, simulated time for the simulator."""

    def now(self) -> float: ...

    def sleep(self, seconds: float) -> None: ...

    def await_stream(self) -> None:
        """The caller is about to wait for the next sample a device streams at its own rate.

        Called right before each such wait (never before the answer to a request). Real
        time passes meanwhile by itself, so the wall clock does nothing; a clock whose time
        passes only while the host waits (the simulator's lockstep clock) lets the served
        stream go on by one sample.
        """
        ...


class WallClock:
    """The real clock."""

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        time.sleep(max(0.0, seconds))

    def await_stream(self) -> None:
        """Nothing to do: the device streams in real time."""


@runtime_checkable
class RotaryAxis(Protocol):
    """One rotary axis of a positioning unit."""

    name: str

    def position_rad(self) -> float:
        """Reported (encoder) angle."""
        ...

    def move_to(self, angle_rad: float) -> None:
        """Release the brake and start a move to a reported angle; returns at once."""
        ...

    def wait_in_position(self, timeout_s: float) -> None: ...

    def stop(self) -> None: ...

    def lock(self) -> None:
        """Stop and apply the brake."""
        ...

    def is_locked(self) -> bool: ...


@runtime_checkable
class PositioningUnit(Protocol):
    """A launch (2 axes) or receiver (3 axes) positioning unit."""

    kind: Literal["launch", "receiver"]

    @property
    def axes(self) -> tuple[RotaryAxis, ...]: ...

    def angles_rad(self) -> Vec:
        """Reported angles of all axes, shape (2,) or (3,)."""
        ...

    def move_to(self, angles_rad: Vec, timeout_s: float) -> None:
        """Move all axes to reported angles and wait until they are in position.

        ``timeout_s`` is one deadline for the whole move (not one per axis).
        """
        ...

    def lock(self) -> None:
        """Stop every axis and apply the brakes."""
        ...


@runtime_checkable
class Interferometer(Protocol):
    """A six-channel interferometer (XM-60 class).

    ``read`` gives the raw channels: ``linear_um`` is the displacement along the
    beam since the last :meth:`zero` (actual, not an error: the run step
    subtracts the commanded displacement), the other five as in docs/conventions.md
    in the frame of the beam (``u`` along the beam from the launch unit).
    """

    def zero(self) -> None:
        """Set the linear displacement datum at the present receiver position."""
        ...

    def read(self) -> InterferometerReading: ...

    def average(self, duration_s: float) -> InterferometerReading:
        """Mean of the readings over ``duration_s``; ``beam_ok`` only if all were."""
        ...


@runtime_checkable
class MachinePositionSource(Protocol):
    """Where the machine's tool point is (CNC coordinates)."""

    def position_mm(self) -> Vec:
        """Current CNC tool point, shape (3,)."""
        ...

    def is_standstill(self) -> bool: ...


@runtime_checkable
class MachineMover(MachinePositionSource, Protocol):
    """A machine that xmalign may command (the simulated CNC, or an operator prompt)."""

    def move_to(self, position_mm: Vec, feed_mm_min: float) -> None:
        """Move the tool point and return when it stands still there."""
        ...


#: A controller's program: not running, running, or stopped mid-program (M0 or feed hold).
ProgramState = Literal["idle", "running", "paused"]


@runtime_checkable
class ProgramControl(MachinePositionSource, Protocol):
    """A controller that runs xmalign's program and lets xmalign start, hold and resume it.

    Only program control: xmalign never writes an axis position through it,
    the controller's own limits and interlocks stay in force. Each method
    returns once the controller has taken the command (DeviceError when it
    refuses one).
    """

    def program_state(self) -> ProgramState: ...

    def check_ready(self) -> None:
        """Raise DriveFaultError unless the machine is on, homed and free of faults."""
        ...

    def loaded_program(self) -> str | None:
        """The path of the program the controller has open, None if none."""
        ...

    def start_program(self, path: str) -> None:
        """Open ``path`` (as the controller sees it) and run it from its first block."""
        ...

    def hold(self) -> None:
        """Feed hold: the machine stops on its path; :meth:`resume` goes on."""
        ...

    def resume(self) -> None:
        """Go on after a programmed stop (M0) or a feed hold."""
        ...

    def stop_program(self) -> None:
        """Abort the program (the machine stops; a new start begins at the top)."""
        ...


@dataclass(frozen=True)
class ProgramReport:
    """The program a followed controller reports: ``name`` as the controller spells it
    (a path, ``/_N_MPF_DIR/_N_XMALIGN_MPF``, ``O1000``; None: no program selected) and
    its state."""

    name: str | None
    state: ProgramState


@runtime_checkable
class ReportsProgram(Protocol):
    """A controller xmalign follows that says which program it has (MTConnect, SINUMERIK)."""

    def program_report(self) -> ProgramReport | None:
        """The program and its state; None when the controller does not report its program."""
        ...


@dataclass(frozen=True)
class EnvironmentReading:
    """One reading of a weather station (XC-80 class): NaN where a sensor gave nothing.

    ``material_temp_c`` holds one value per material sensor (up to three), °C.
    """

    time_s: float
    air_temp_c: float
    air_pressure_hpa: float
    air_humidity_percent: float
    material_temp_c: tuple[float, ...] = ()


@runtime_checkable
class EnvironmentSource(Protocol):
    """Where the air and material conditions come from: typed values, a file or a station.

    ``read`` raises :class:`xmalign.errors.DeviceTimeoutError` (or another
    ``TransportError``) when the source does not answer.
    """

    def read(self) -> EnvironmentReading: ...


def move_axes(
    axes: Sequence[RotaryAxis],
    angles_rad: Sequence[float] | Vec,
    timeout_s: float,
    device: str,
    clock: Clock,
) -> None:
    """Start every axis towards its reported angle, then wait until all are in position.

    ``timeout_s`` is one deadline for the whole move, counted on ``clock`` from
    this call: each axis waits for what is left of it (every implementation of
    ``PositioningUnit.move_to`` means this). Raises InputError when the number
    of angles is not the number of axes.
    """
    angles = np.asarray(angles_rad, dtype=float)
    if angles.shape != (len(axes),):
        raise InputError(f"{device}: expected {len(axes)} angles, got {angles.size}")
    deadline_s = clock.now() + timeout_s
    for axis, angle in zip(axes, angles, strict=True):
        axis.move_to(float(angle))
    for axis in axes:
        axis.wait_in_position(max(0.0, deadline_s - clock.now()))


def mean_reading(readings: list[InterferometerReading]) -> InterferometerReading:
    """Average of readings (time of the last one); ``beam_ok`` only if all were."""
    channels = np.mean([r.channels for r in readings], axis=0)
    signals = [r.signal_pct for r in readings if r.signal_pct is not None]
    return InterferometerReading(
        time_s=readings[-1].time_s,
        channels=channels,
        beam_ok=all(r.beam_ok for r in readings),
        signal_pct=float(np.mean(signals)) if len(signals) == len(readings) else None,
    )


class ClosesOnExit:
    """Mixin: an object holding a connection or a file is a context manager that
    calls its ``close()`` on exit (``with open_devices(...) as devices:``)."""

    def close(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
