"""Simulated positioning units with the firmware semantics of docs/registers.md.

:class:`SimAxis` is one axis (drive + brake + encoder), evaluated analytically
at ``clock.now()``; :class:`SimUnit` holds the axes of a launch (2) or receiver
(3) unit, the register image served over Modbus, the heartbeat watchdog and the
unit's true geometry; :class:`SimPositioningUnit` is the in-process
``PositioningUnit`` role on top of it (it is the host, so it beats too). Angles
inside are rad; the registers speak encoder counts.

Firmware rules (docs/registers.md): ``start``, ``home`` and ``fault_reset`` act
on their rising edge; ``start`` needs ``enable | unlock`` and no fault;
clearing ``unlock`` stops the axis and it is locked once at rest; a stop never
rewrites the target, so "in position" means at the target the host wrote. The
watchdog runs from power-on: 350 ms after the last change of the heartbeat
register (or power-on) every axis quick-stops and brakes (fault 4), so it is at
rest and locked by 500 ms. Until the heartbeat has changed (after power-on, and
again after every expiry) the watchdog is not armed: every control bit but
``stop`` is ignored (no enable, unlock, start, home, track nor fault reset), so
fault 4 stays and nothing moves until the host is beating again.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike

from firmware_iface.register_map import (
    Control,
    Register,
    RegisterMap,
    Status,
    load_register_map,
)
from firmware_iface.unit import HEARTBEAT_FAULT, axis_fault
from sim import motion
from sim.clock import SimClock
from sim.imperfections import UnitImperfections
from xmalign.errors import (
    DeviceTimeoutError,
    InputError,
    OutOfRangeError,
)
from xmalign.geometry import Vec, rot_x, rot_y, rot_z
from xmalign.roles import Clock, move_axes

log = logging.getLogger(__name__)

COUNTS_PER_REV = 1 << 23
FIRMWARE_VERSION = 0x0100
FAULT_NOT_HOMED = 6
FAULT_NO_TRACKING = 7
IN_POSITION_COUNTS = 2


@dataclass(frozen=True)
class AxisLimits:
    """Range (rad), maximum velocity (rad/s) and acceleration (rad/s²) of one axis."""

    min_rad: float
    max_rad: float
    max_velocity_rad_s: float = math.radians(30.0)
    acceleration_rad_s2: float = math.radians(90.0)


#: Azimuth axes turn three quarters of a turn either way (cable-limited, as real units),
#: so a correction across ±180° never needs a full turn back.
_FULL_TURN = AxisLimits(-math.radians(270.0), math.radians(270.0))
#: Tilt axes reach a little past vertical, so a vertical line (exactly ±90°) stays
#: commandable whatever the encoder zero offset.
_TILT = AxisLimits(-math.radians(100.0), math.radians(100.0))
AXIS_LIMITS = {"launch": (_FULL_TURN, _TILT), "receiver": (_FULL_TURN, _TILT, _FULL_TURN)}
AXIS_NAMES = {"launch": ("a1", "a2"), "receiver": ("a3", "a4", "a5")}


def rad_to_counts(angle_rad: float) -> int:
    return round(angle_rad * COUNTS_PER_REV / (2.0 * math.pi))


def counts_to_rad(counts: int) -> float:
    return counts * 2.0 * math.pi / COUNTS_PER_REV


class SimAxis:
    """One simulated axis: trapezoidal drive, brake, encoder, homing and faults.

    The motor angle is kept in the homed encoder frame; the reported angle is
    the motor angle (minus the power-on offset until homed) plus encoder noise;
    the true head angle adds the zero offset and the belt backlash.
    """

    def __init__(
        self,
        name: str,
        clock: Clock,
        limits: AxisLimits,
        zero_offset_rad: float,
        backlash_rad: float,
        encoder_noise_rad: float,
        rng: np.random.Generator,
        homed: bool = True,
    ) -> None:
        self.name = name
        self.clock = clock
        self.limits = limits
        self.zero_offset_rad = zero_offset_rad
        self.backlash_rad = backlash_rad
        self.encoder_noise_rad = encoder_noise_rad
        self._rng = rng
        self.profile = motion.rest(0.0, clock.now())
        self.velocity_limit_rad_s = limits.max_velocity_rad_s
        self.enabled = False
        self.unlocked = False
        self.homed = homed
        self.power_on_offset_rad = 0.0 if homed else float(rng.uniform(-0.5, 0.5))
        self.fault_code = 0
        self.target_rad = 0.0
        self._homing = False
        self._last_direction = 1.0

    # state ------------------------------------------------------------------
    def motor_rad(self, time_s: float | None = None) -> float:
        return self.profile.state(self.clock.now() if time_s is None else time_s)[0]

    def is_moving(self) -> bool:
        return self.profile.is_moving(self.clock.now())

    def reported_rad(self) -> float:
        """Encoder reading (with noise)."""
        noise = self._rng.normal(0.0, self.encoder_noise_rad) if self.encoder_noise_rad else 0.0
        return self.motor_rad() - (0.0 if self.homed else self.power_on_offset_rad) + noise

    def true_rad(self) -> float:
        """True head angle: motor plus zero offset, lagging by half the backlash."""
        now = self.clock.now()
        velocity = self.profile.state(now)[1]
        if velocity != 0.0:
            self._last_direction = math.copysign(1.0, velocity)
        elif self.profile.segments[-1].position != self.profile.segments[0].position:
            self._last_direction = math.copysign(
                1.0, self.profile.segments[-1].position - self.profile.segments[0].position
            )
        return (
            self.motor_rad(now)
            + self.zero_offset_rad
            - 0.5 * self.backlash_rad * (self._last_direction)
        )

    def in_position(self) -> bool:
        if self.is_moving():
            return False
        return abs(rad_to_counts(self.motor_rad() - self.target_rad)) <= IN_POSITION_COUNTS

    def is_locked(self) -> bool:
        return not self.unlocked and not self.is_moving()

    def at_limit(self) -> bool:
        angle = self.motor_rad()
        tolerance = counts_to_rad(IN_POSITION_COUNTS)
        return angle <= self.limits.min_rad + tolerance or angle >= self.limits.max_rad - tolerance

    def status(self) -> Status:
        if self._homing and not self.is_moving():
            self._homing = False
            self.homed = True
            self.power_on_offset_rad = 0.0
        bits = Status(0)
        for flag, on in (
            (Status.ENABLED, self.enabled),
            (Status.IN_POSITION, self.in_position()),
            (Status.MOVING, self.is_moving()),
            (Status.FAULT, self.fault_code != 0),
            (Status.LOCKED, self.is_locked()),
            (Status.HOMED, self.homed),
            (Status.AT_LIMIT, self.at_limit()),
        ):
            if on:
                bits |= flag
        return bits

    # commands ---------------------------------------------------------------
    def check_target(self, reported_rad: float) -> float:
        """The motor angle of a reported target; OutOfRangeError outside the axis range."""
        motor = reported_rad + (0.0 if self.homed else self.power_on_offset_rad)
        if not self.limits.min_rad <= motor <= self.limits.max_rad:
            raise OutOfRangeError(
                f"axis {self.name}: target {math.degrees(reported_rad):.4f} deg outside "
                f"[{math.degrees(self.limits.min_rad):g}, "
                f"{math.degrees(self.limits.max_rad):g}] deg"
            )
        return motor

    def set_target(self, reported_rad: float) -> None:
        self.target_rad = self.check_target(reported_rad)

    def set_velocity_limit(self, velocity_rad_s: float) -> None:
        if not 0.0 < velocity_rad_s <= self.limits.max_velocity_rad_s * (1 + 1e-9):
            raise OutOfRangeError(
                f"axis {self.name}: velocity limit {math.degrees(velocity_rad_s):g} deg/s outside "
                f"(0, {math.degrees(self.limits.max_velocity_rad_s):g}] deg/s"
            )
        self.velocity_limit_rad_s = velocity_rad_s

    def can_move(self) -> bool:
        return self.enabled and self.unlocked and self.fault_code == 0

    def start(self) -> None:
        """Start the move to the target (ignored unless enabled, unlocked and not faulted)."""
        if not self.can_move():
            return
        if not self.homed:
            self.fault(FAULT_NOT_HOMED)
            return
        self.profile = motion.move(
            self.profile,
            self.clock.now(),
            self.target_rad,
            self.velocity_limit_rad_s,
            self.limits.acceleration_rad_s2,
        )

    def run_at(self, velocity_rad_s: float) -> None:
        """Velocity mode: run at a constant velocity (clipped to the limit) until stopped."""
        if not self.can_move():
            return
        velocity = float(
            np.clip(velocity_rad_s, -self.velocity_limit_rad_s, self.velocity_limit_rad_s)
        )
        self.profile = motion.cruise(
            self.profile, self.clock.now(), velocity, self.limits.acceleration_rad_s2
        )

    def home(self) -> None:
        """Run to the reference mark (motor angle 0); homed once there."""
        if not self.can_move():
            return
        self._homing = True
        self.target_rad = 0.0
        self.profile = motion.move(
            self.profile,
            self.clock.now(),
            0.0,
            self.velocity_limit_rad_s,
            self.limits.acceleration_rad_s2,
        )

    def stop(self, time_s: float | None = None, deceleration_rad_s2: float | None = None) -> None:
        """Decelerate to rest from the state at ``time_s`` (default now).

        ``deceleration_rad_s2`` defaults to the axis's acceleration (a quick stop is faster).
        """
        when = self.clock.now() if time_s is None else time_s
        deceleration = deceleration_rad_s2 or self.limits.acceleration_rad_s2
        self.profile = motion.stop(self.profile, when, deceleration)
        self._homing = False

    def fault(
        self, code: int, time_s: float | None = None, deceleration_rad_s2: float | None = None
    ) -> None:
        """Stop, apply the brake (on rest) and report ``code``."""
        self.stop(time_s, deceleration_rad_s2)
        self.unlocked = False
        self.fault_code = code

    def reset_fault(self) -> None:
        self.fault_code = 0


#: The control bits a unit ignores while its watchdog is not armed (no heartbeat since
#: power-on or since the watchdog expired): all but ``stop``.
NEEDS_HEARTBEAT = (
    Control.ENABLE
    | Control.UNLOCK
    | Control.START
    | Control.FAULT_RESET
    | Control.HOME
    | Control.TRACK
)
_DEFINED_CONTROL_BITS = sum(int(bit) for bit in Control)


@dataclass(frozen=True)
class _Edges:
    rising: Control
    value: Control


class SimUnit:
    """A simulated launch or receiver unit: axes, register image, watchdog and geometry.

    Parameters
    ----------
    kind : {"launch", "receiver"}
    clock : Clock
        Virtual (:class:`~sim.clock.SimClock`) or real-time.
    imperfections : UnitImperfections, optional
    seed : int, optional
        Seeds the encoder noise (and the power-on angle when not homed).
    homed : bool
        Whether the unit starts homed (a real one must be homed after power-on).
    """

    def __init__(
        self,
        kind: Literal["launch", "receiver"],
        clock: Clock | None = None,
        imperfections: UnitImperfections | None = None,
        seed: int | None = None,
        homed: bool = True,
        register_map: RegisterMap | None = None,
    ) -> None:
        if kind not in AXIS_LIMITS:
            raise InputError(f"unit kind must be 'launch' or 'receiver', not '{kind}'")
        self.kind = kind
        self.clock = clock or SimClock()
        self.imperfections = imperfections or UnitImperfections()
        self.register_map = register_map or load_register_map()
        rng = np.random.default_rng(seed)
        offsets = np.resize(np.asarray(self.imperfections.zero_offsets_rad, dtype=float), 3)
        if kind == "launch":
            offsets[0] = 0.0  # c1 is absorbed in gamma (docs/conventions.md)
        self.axes = tuple(
            SimAxis(
                name,
                self.clock,
                limits,
                float(offsets[i]),
                self.imperfections.backlash_rad,
                self.imperfections.encoder_noise_rad,
                rng,
                homed,
            )
            for i, (name, limits) in enumerate(
                zip(AXIS_NAMES[kind], AXIS_LIMITS[kind], strict=True)
            )
        )
        self._control = [Control(0)] * len(self.axes)
        self._heartbeat = 0
        #: The watchdog is armed: the heartbeat changed since power-on and since its last expiry.
        self.heartbeat_seen = False
        self._heartbeat_time_s = self.clock.now()
        self._watchdog_tripped = False
        self._host_beating = False
        self.lock = threading.RLock()

    # watchdog ---------------------------------------------------------------
    def heartbeat(self, value: int) -> None:
        """The host's heartbeat register; a change (from power-on 0 too) re-arms the watchdog."""
        with self.lock:
            self.check_watchdog()
            if value != self._heartbeat:
                self._heartbeat = value
                self._arm_watchdog()

    def heartbeat_age_s(self) -> float:
        """Time since the heartbeat last changed (or power-on), on the unit's clock."""
        with self.lock:
            self.check_watchdog()
            return self.clock.now() - self._heartbeat_time_s

    def _arm_watchdog(self) -> None:
        """A heartbeat: the watchdog counts from now, and a fault reset is accepted again."""
        self._heartbeat_time_s = self.clock.now()
        self.heartbeat_seen = True
        self._watchdog_tripped = False

    def keep_heartbeat(self, on: bool) -> None:
        """An in-process host's background heartbeat: while on, the heartbeat is never stale.

        Stands for the drivers' heartbeat thread, which virtual time would outrun;
        the register keeps the value the host last wrote.
        """
        with self.lock:
            self.check_watchdog()
            if on or self._host_beating:
                self._arm_watchdog()
            self._host_beating = on

    def check_watchdog(self) -> None:
        """Quick-stop and brake every axis (fault 4) once the heartbeat is stale.

        Evaluated retroactively: the stop begins at the expiry, however late it is noticed.
        The watchdog is then disarmed until the heartbeat changes again (:meth:`control`).
        """
        if self._host_beating:
            self._heartbeat_time_s = self.clock.now()
        if self._watchdog_tripped:
            return
        expiry_s = self._heartbeat_time_s + self.register_map.quick_stop_start_s
        if self.clock.now() >= expiry_s:
            self._watchdog_tripped = True
            self.heartbeat_seen = False
            log.warning(
                "%s unit: heartbeat watchdog expired: no heartbeat for %.0f ms; every axis"
                " quick-stopped and locked (fault 4)",
                self.kind,
                1000.0 * (self.clock.now() - self._heartbeat_time_s),
            )
            for axis in self.axes:
                axis.fault(HEARTBEAT_FAULT, expiry_s, self.register_map.quick_stop_rad_s2)
            self._control = [c & ~Control.UNLOCK for c in self._control]

    # register-level API -------------------------------------------------------
    def read_registers(self, address: int, count: int) -> list[int]:
        """Holding registers ``address .. address + count - 1`` (unused addresses read 0)."""
        with self.lock:
            self.check_watchdog()
            image = self._image()
            if address < 0 or count < 1 or address + count > self._register_count():
                raise InputError(
                    f"registers {address}..{address + count - 1} "
                    f"outside 0..{self._register_count() - 1}"
                )
            return [image.get(a, 0) for a in range(address, address + count)]

    def write_registers(self, address: int, values: list[int]) -> None:
        """Write holding registers; OutOfRangeError for a bad value, InputError for read-only.

        The whole write is validated before anything changes.
        """
        with self.lock:
            self.check_watchdog()
            words = dict(enumerate(values, start=address))
            actions = [self._decode_write(name, axis, words) for name, axis in self._written(words)]
            for action in actions:
                action()

    def _register_count(self) -> int:
        return self.register_map.axis_stride * (len(self.axes) + 1)

    def _written(self, words: dict[int, int]) -> list[tuple[str, int]]:
        """The registers (name, axis number or 0) a write touches; InputError if not writable
        or if it covers only one word of a 32-bit register (a value is written whole)."""
        touched: list[tuple[str, int]] = []
        for address in words:
            name, axis = self._register_at(address)
            if (name, axis) not in touched:
                touched.append((name, axis))
        for name, axis in touched:
            reg = self._register(name, axis)
            if any(a not in words for a in range(reg.address, reg.address + reg.width)):
                raise InputError(
                    f"register {reg.address} ({reg.name}) is 32 bits: write both words"
                    f" ({reg.address}-{reg.address + 1}) in one request"
                )
        return touched

    def _register(self, name: str, axis: int) -> Register:
        """Register ``name`` of axis ``axis``, or of the device for axis 0."""
        return self.register_map.axis(axis, name) if axis else self.register_map.device[name]

    def _register_at(self, address: int) -> tuple[str, int]:
        rmap = self.register_map
        candidates = [(name, 0, reg) for name, reg in rmap.device.items()] + [
            (name, n, rmap.axis(n, name))
            for n in range(1, len(self.axes) + 1)
            for name in rmap.axis_registers
        ]
        for name, axis, reg in candidates:
            if reg.address <= address < reg.address + reg.width:
                if "w" not in reg.access:
                    raise InputError(f"register {address} ({reg.name}) is read-only")
                return name, axis
        raise InputError(f"register {address} is not a register of the {self.kind} unit")

    def _value(self, name: str, axis: int, words: dict[int, int]) -> int:
        reg = self._register(name, axis)
        raw = [words[a] & 0xFFFF for a in range(reg.address, reg.address + reg.width)]
        if reg.width == 1:
            return raw[0]
        value = (raw[0] << 16) | raw[1]
        return value - (1 << 32) if reg.type == "int32" and value >= 1 << 31 else value

    def _decode_write(self, name: str, n: int, words: dict[int, int]) -> Callable[[], None]:
        value = self._value(name, n, words)
        if name == "heartbeat":
            return lambda: self.heartbeat(value)
        axis = self.axes[n - 1]
        if name == "target":
            axis.check_target(counts_to_rad(value))
            return lambda: axis.set_target(counts_to_rad(value))
        if name == "velocity_limit":
            if value <= 0 or counts_to_rad(value) > axis.limits.max_velocity_rad_s * (1 + 1e-6):
                raise OutOfRangeError(
                    f"axis {axis.name}: velocity limit {value} counts/s out of range"
                )
            return lambda: axis.set_velocity_limit(
                min(counts_to_rad(value), axis.limits.max_velocity_rad_s)
            )
        undefined = value & ~_DEFINED_CONTROL_BITS
        if undefined:
            raise OutOfRangeError(
                f"axis {axis.name}: control bits {undefined:#06x} are not defined (bits 0-6 are)"
            )
        return lambda: self.control(n, Control(value))

    def control(self, n: int, value: Control) -> None:
        """Apply a control-register write to axis ``n`` (1-based)."""
        with self.lock:
            self.check_watchdog()
            if not self.heartbeat_seen:  # the watchdog is not armed: nothing but stop
                value &= ~NEEDS_HEARTBEAT
            axis = self.axes[n - 1]
            edges = _Edges(rising=value & ~self._control[n - 1], value=value)
            self._control[n - 1] = value
            if Control.FAULT_RESET in edges.rising:
                axis.reset_fault()
            axis.enabled = Control.ENABLE in value
            halt = not axis.enabled or Control.UNLOCK not in value or Control.STOP in value
            if halt and axis.is_moving():
                axis.stop()
            axis.unlocked = axis.enabled and Control.UNLOCK in value and axis.fault_code == 0
            if Control.TRACK in edges.rising:
                axis.fault(FAULT_NO_TRACKING)
            if Control.HOME in edges.rising:
                axis.home()
            elif Control.START in edges.rising and Control.STOP not in value:
                axis.start()

    def quick_stop(self, n: int) -> None:
        """Stop axis ``n`` at the quick-stop deceleration; it is disabled and locked at rest."""
        with self.lock:
            self.control(n, Control(0))
            self.axes[n - 1].stop(deceleration_rad_s2=self.register_map.quick_stop_rad_s2)

    def _image(self) -> dict[int, int]:
        """The register image: address -> 16-bit word."""
        rmap = self.register_map
        image: dict[int, int] = {}

        def put(address: int, type_: str, value: int) -> None:
            if type_ == "uint16":
                image[address] = value & 0xFFFF
            else:
                value &= 0xFFFFFFFF
                image[address], image[address + 1] = value >> 16, value & 0xFFFF

        device = rmap.device
        put(device["device_type"].address, "uint16", rmap.device_types[self.kind])
        put(device["firmware_version"].address, "uint16", FIRMWARE_VERSION)
        put(device["axis_count"].address, "uint16", len(self.axes))
        put(device["heartbeat"].address, "uint16", self._heartbeat)
        put(device["counts_per_rev"].address, "uint32", COUNTS_PER_REV)
        for n, axis in enumerate(self.axes, start=1):
            values = {
                "control": int(self._control[n - 1]),
                "status": int(axis.status()),
                "target": rad_to_counts(
                    axis.target_rad - (0.0 if axis.homed else axis.power_on_offset_rad)
                ),
                "actual": rad_to_counts(axis.reported_rad()),
                "velocity_limit": rad_to_counts(axis.velocity_limit_rad_s),
                "fault_code": axis.fault_code,
            }
            for name, value in values.items():
                reg = rmap.axis(n, name)
                put(reg.address, reg.type, value)
        return image

    # axis-level API (for the CiA 402 node and in-process use) ------------------
    def reported_rad(self) -> Vec:
        """Reported (encoder) angles of all axes, shape (n_axes,)."""
        with self.lock:
            self.check_watchdog()
            return np.array([axis.reported_rad() for axis in self.axes])

    def true_rad(self) -> Vec:
        """True axis angles (zero offsets, backlash), shape (n_axes,)."""
        with self.lock:
            self.check_watchdog()
            return np.array([axis.true_rad() for axis in self.axes])

    def is_still(self) -> bool:
        """No axis is moving."""
        with self.lock:
            self.check_watchdog()
            return not any(axis.is_moving() for axis in self.axes)

    # true geometry ----------------------------------------------------------------
    def head_rotation(self, mount_rotation: Vec) -> Vec:
        """Rotation of the head (launch) or receiver in the MCS, shape (3, 3).

        ``mount_rotation`` is the unit base's rotation: ``Rz(gamma)`` for the
        launch unit, the tool's rotation times ``Rz(gamma_R)`` for the receiver.
        Launch: ``Rz(phi1)·Ry(-phi2)·B``; receiver ``Rz(phi3)·Ry(-phi4)·Rx(phi5)·B``
        with true angles and ``B`` the beam misalignment (small rotation).
        """
        angles = self.true_rad()
        rotation = mount_rotation @ rot_z(angles[0]) @ rot_y(-angles[1])
        if self.kind == "receiver":
            rotation = rotation @ rot_x(angles[2])
        tilt_y, tilt_z = self.imperfections.beam_misalignment_rad
        return rotation @ rot_y(tilt_y) @ rot_z(tilt_z)

    def optical_centre(self, cp_mm: Vec, head_rotation: Vec) -> Vec:
        """Where the beam leaves (launch) or is measured (receiver), MCS mm, shape (3,)."""
        return np.asarray(cp_mm, dtype=float) + head_rotation @ self.imperfections.axis_offset_mm


class _SimRotaryAxis:
    """The ``RotaryAxis`` role for axis ``n`` of a :class:`SimUnit` (angles are reported rad).

    It is the host's side: every call beats the shared heartbeat, and waits beat
    at least every half heartbeat period, as the drivers do.
    """

    def __init__(self, host: SimPositioningUnit, n: int) -> None:
        self.host = host
        self.unit = host.unit
        self.n = n
        self.name = self.unit.axes[n - 1].name

    @property
    def _axis(self) -> SimAxis:
        return self.unit.axes[self.n - 1]

    def position_rad(self) -> float:
        self.host.beat()
        with self.unit.lock:
            self.unit.check_watchdog()
            return self._axis.reported_rad()

    def move_to(self, angle_rad: float) -> None:
        self.host.beat()
        with self.unit.lock:
            self._raise_fault()
            self._axis.set_target(angle_rad)
            self.unit.control(self.n, Control.ENABLE | Control.UNLOCK)
            self.unit.control(self.n, Control.ENABLE | Control.UNLOCK | Control.START)
            self._raise_fault()

    def wait_in_position(self, timeout_s: float) -> None:
        clock = self.unit.clock
        deadline_s = clock.now() + timeout_s
        step_s = self.unit.register_map.heartbeat_period_s / 2.0
        while True:
            self.host.beat()
            with self.unit.lock:
                self._raise_fault()
                remaining_s = self._axis.profile.end_s - clock.now()
                if remaining_s <= 0.0 and self._axis.in_position():
                    return
            if clock.now() >= deadline_s:
                raise DeviceTimeoutError(f"axis {self.name} not in position after {timeout_s:g} s")
            # at rest short of the target (stopped): nothing will change before the deadline
            wait_s = remaining_s if remaining_s > 0.0 else deadline_s - clock.now()
            clock.sleep(min(wait_s, step_s, deadline_s - clock.now()))

    def stop(self) -> None:
        self.host.beat()
        with self.unit.lock:
            self.unit.control(self.n, Control.ENABLE | Control.UNLOCK | Control.STOP)

    def lock(self) -> None:
        self.host.beat()
        with self.unit.lock:
            self.unit.control(self.n, Control.ENABLE)

    def is_locked(self) -> bool:
        self.host.beat()
        with self.unit.lock:
            return self._axis.is_locked()

    def enable(self) -> None:
        self.host.beat()
        self.unit.control(self.n, Control.ENABLE)

    def fault_code(self) -> int:
        self.host.beat()
        with self.unit.lock:
            self.unit.check_watchdog()
            return self._axis.fault_code

    def reset_fault(self) -> None:
        self.host.beat(now=True)  # the unit takes a fault reset only with the heartbeat running
        self.unit.control(self.n, Control.ENABLE | Control.FAULT_RESET)
        self.unit.control(self.n, Control.ENABLE)

    def _raise_fault(self) -> None:
        self.unit.check_watchdog()
        if self._axis.fault_code:
            label = f"axis {self.name} of the simulated {self.unit.kind} unit"
            raise axis_fault(label, self._axis.fault_code)


class SimPositioningUnit:
    """In-process ``PositioningUnit`` on a :class:`SimUnit` (reported angles, rad).

    It implements the role on its own, not through the drivers' ``AxisGroup``, so
    the unit contract suite (tests/firmware_iface/test_unit_contract.py) compares
    two implementations and catches a bug they would share. It plays the host: it
    changes the unit's heartbeat from every call (at most every half heartbeat
    period of the unit's clock) and, like the drivers opened
    from a ``units.yaml``, keeps a background heartbeat until :meth:`stop_heartbeat`
    (a host that stalls or closes). Opening it clears a heartbeat fault left from
    power-on, as the drivers do when they connect.
    """

    def __init__(self, unit: SimUnit) -> None:
        self.unit = unit
        self.kind = unit.kind
        self.clock = unit.clock
        self.device_name = f"simulated {unit.kind} unit"
        self._heartbeat_value = 0
        self._last_beat_s = -math.inf
        self._axes = tuple(_SimRotaryAxis(self, n) for n in range(1, len(unit.axes) + 1))
        self.beat()
        self.unit.keep_heartbeat(True)
        for axis in self._axes:  # a heartbeat fault left from power-on; the axes stay locked
            if axis.fault_code() == HEARTBEAT_FAULT:
                axis.reset_fault()

    @property
    def axes(self) -> tuple[_SimRotaryAxis, ...]:
        return self._axes

    def lock(self) -> None:
        """Stop every axis and apply the brakes."""
        for axis in self._axes:
            axis.lock()

    def reset_faults(self) -> None:
        """Reset every axis's fault (as the drivers' ``reset_faults``); the axes stay locked."""
        for axis in self._axes:
            axis.reset_fault()

    def stop_heartbeat(self) -> None:
        """Stop the background heartbeat; the calls still beat."""
        self.unit.keep_heartbeat(False)

    def beat(self, now: bool = False) -> None:
        """Change the heartbeat if half a heartbeat period has passed on the unit's clock.

        ``now``: change it whenever it last changed (before a fault reset).
        """
        time_s = self.clock.now()
        if not now and time_s - self._last_beat_s < self.unit.register_map.heartbeat_period_s / 2:
            return
        self._last_beat_s = time_s
        self._heartbeat_value = self._heartbeat_value % 0xFFFF + 1
        self.unit.heartbeat(self._heartbeat_value)

    def angles_rad(self) -> Vec:
        self.beat()
        return self.unit.reported_rad()

    def move_to(self, angles_rad: ArrayLike, timeout_s: float) -> None:
        """Move every axis; nothing moves if a target is out of range (one deadline per move)."""
        targets = np.asarray(angles_rad, dtype=float)
        if targets.shape == (len(self._axes),):
            for axis, target in zip(self._axes, targets, strict=True):
                axis._axis.check_target(float(target))
        move_axes(self._axes, targets, timeout_s, self.device_name, self.clock)
