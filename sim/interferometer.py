"""The simulated six-channel interferometer (XM-60 class) of docs/conventions.md.

The reading follows from the true geometry: the launch head's beam (unit
angles, zero offsets, axis offset, beam misalignment), the receiver carried by
the virtual machine's actual tool pose, and the CNC position. Channels are in
the beam's line frame (``xmalign.geometry.line_frame`` of the beam direction):
``linear_um`` is the displacement along the beam since :meth:`zero`, counted
as an optical path (the air's refractive index times the length) when the
interferometer sees a :class:`sim.environment.SimEnvironment` (whose thermal
growth also moves the receiver),
straightness the receiver's optical centre relative to the beam, angles the
receiver's rotation relative to the launch head (zero when the units face each
other with roll 0).

The receiver sees the beam (its signal strength, 0 to 100 %) wider than the
channels' ranges: while the beam passes within the machine file's
``interferometer.capture_radius_mm`` of the receiver's optical centre and the
receiver faces it within ``capture_angle_mrad``, the strength falls from 100 %
(centred, facing) to 0 at either edge, ``(1 - (r/R)^2) (1 - (theta/Theta)^2)``;
a blocked beam gives none. The search for the first alignment looks for it.

Like a real interferometer it loses its linear count when the beam is
interrupted: when a reading finds the beam out of range after it was in
range, the datum moves by an unknown amount (up to a millimetre), until
:meth:`zero` sets it again.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from sim.environment import SimEnvironment
from sim.machine import VirtualMachine
from sim.units import SimUnit
from xmalign.errors import InputError
from xmalign.geometry import Vec, rot_z
from xmalign.machine import InterferometerRanges
from xmalign.roles import Clock, InterferometerReading, MachinePositionSource, mean_reading

UM_PER_MM = 1000.0
URAD_PER_RAD = 1e6
#: The receiver faces the launch head: its frame is the head's turned half a turn about z.
_FACING = rot_z(np.pi)


@dataclass(frozen=True)
class InterferometerNoise:
    """Standard deviation of one sample per channel (XM-60 class; docs/conventions-notes.md)."""

    linear_um: float = 0.02
    straightness_um: float = 0.2
    angle_urad: float = 0.1
    roll_urad: float = 0.5

    def sigmas(self) -> Vec:
        """Per channel, in the order of :data:`xmalign.roles.CHANNELS`, shape (6,)."""
        s = self.straightness_um
        a = self.angle_urad
        return np.array([self.linear_um, s, s, self.roll_urad, a, a])


@dataclass(frozen=True)
class Geometry:
    """True, noise-free state: channels (6,) with the full optical path in ``linear``, beam status.

    ``distance_mm`` is the geometric launch-to-receiver distance along the beam,
    ``signal_pct`` the receiver's signal strength.
    """

    distance_mm: float
    channels: Vec
    beam_ok: bool
    signal_pct: float = 0.0

    @property
    def optical_mm(self) -> float:
        return float(self.channels[0]) / UM_PER_MM


class SimInterferometer:
    """``Interferometer`` role on the simulated units, machine and CNC.

    Parameters
    ----------
    launch, receiver : SimUnit
    machine : VirtualMachine
    position : MachinePositionSource
        Where the CNC is (the simulated CNC).
    launch2mcs_mm : array_like, shape (3,)
        True launch cp in the MCS, mm.
    gamma_rad : float
        True launch azimuth.
    clock : Clock, optional
        Defaults to the launch unit's clock.
    ranges : InterferometerRanges, optional
        Defaults to the machine file's ``interferometer`` section.
    noise : InterferometerNoise, optional
    rate_hz : float
        Sample rate of the stream that :meth:`average` uses.
    seed : int, optional
    environment : SimEnvironment, optional
        The shop's air and thermal growth; None: vacuum-like air at 20 °C.
    """

    def __init__(
        self,
        launch: SimUnit,
        receiver: SimUnit,
        machine: VirtualMachine,
        position: MachinePositionSource,
        launch2mcs_mm: ArrayLike,
        gamma_rad: float,
        clock: Clock | None = None,
        ranges: InterferometerRanges | None = None,
        noise: InterferometerNoise | None = None,
        rate_hz: float = 50.0,
        seed: int | None = None,
        environment: SimEnvironment | None = None,
    ) -> None:
        if launch.kind != "launch" or receiver.kind != "receiver":
            raise InputError("SimInterferometer needs a launch unit and a receiver unit")
        self.launch = launch
        self.receiver = receiver
        self.machine = machine
        self.position = position
        self.launch2mcs_mm = np.asarray(launch2mcs_mm, dtype=float)
        self.gamma_rad = float(gamma_rad)
        self.clock = clock or launch.clock
        self.ranges = ranges or machine.machine.interferometer
        self.noise = noise or InterferometerNoise()
        self.rate_hz = rate_hz
        self._rng = np.random.default_rng(seed)
        self._datum_mm = 0.0
        self.environment = environment
        self._blocked_until_s = -np.inf
        self._counting = True

    def geometry(self) -> Geometry:
        """The noise-free reading now."""
        setup = self.machine.machine
        head = self.launch.head_rotation(rot_z(self.gamma_rad))
        origin = self.launch.optical_centre(self.launch2mcs_mm, head)
        offset = rot_z(setup.spindle_angle_rad) @ setup.receiver_offset
        position = self.position.position_mm()
        cp, tool_rotation = self.machine.tool_pose(position, offset)
        index = 1.0
        if self.environment is not None:
            cp = cp + self.environment.growth_mm(position)
            index = self.environment.air_index()
        mount = Rotation.from_rotvec(tool_rotation).as_matrix() @ rot_z(setup.spindle_angle_rad)
        receiver = self.receiver.head_rotation(mount)
        centre = self.receiver.optical_centre(cp, receiver)
        frame = head.T  # the launch head's axes: the line frame of its beam, turning with it
        along, across_v, across_w = frame @ (centre - origin)
        relative = Rotation.from_matrix(head.T @ receiver @ _FACING.T).as_rotvec()
        angles = frame @ (head @ relative)
        channels = np.concatenate([[along, across_v, across_w], angles * URAD_PER_RAD])
        channels[:3] *= UM_PER_MM
        channels[0] *= index
        return Geometry(
            float(along),
            channels,
            self._in_range(float(along), channels),
            self._signal_pct(float(along), np.hypot(across_v, across_w), angles[1:]),
        )

    def _signal_pct(self, along_mm: float, off_centre_mm: float, tilt_rad: Vec) -> float:
        """Signal strength of a beam ``off_centre_mm`` from the receiver's centre reaching a
        receiver tilted by ``tilt_rad`` (v, w) from facing it, %."""
        r = self.ranges
        if self.clock.now() < self._blocked_until_s or not 0.0 < along_mm <= r.max_range_mm:
            return 0.0
        aperture = 1.0 - (off_centre_mm / r.capture_radius_mm) ** 2
        facing = 1.0 - (float(np.hypot(*tilt_rad)) * 1e3 / r.capture_angle_mrad) ** 2
        return 100.0 * max(aperture, 0.0) * max(facing, 0.0)

    def interrupt(self, duration_s: float) -> None:
        """Block the beam from now for ``duration_s`` (someone or something crosses it)."""
        self._blocked_until_s = self.clock.now() + duration_s

    def _in_range(self, along_mm: float, channels: Vec) -> bool:
        r = self.ranges
        return bool(
            self.clock.now() >= self._blocked_until_s
            and 0.0 < along_mm <= r.max_range_mm
            and np.hypot(channels[1], channels[2]) <= r.straightness_range_um
            and np.all(np.abs(channels[3:]) <= r.angle_range_urad)
        )

    def zero(self) -> None:
        """Set the linear datum (its optical path) at the receiver's present position."""
        geometry = self.geometry()
        self._datum_mm = geometry.optical_mm
        self._counting = geometry.beam_ok

    def _reading(self, geometry: Geometry, noise: Vec, time_s: float) -> InterferometerReading:
        if self._counting and not geometry.beam_ok:
            self._datum_mm += float(self._rng.uniform(-1.0, 1.0))
        self._counting = geometry.beam_ok
        channels = geometry.channels + noise
        channels[0] -= self._datum_mm * UM_PER_MM
        return InterferometerReading(
            time_s=time_s,
            channels=channels,
            beam_ok=geometry.beam_ok,
            signal_pct=geometry.signal_pct,
        )

    def read(self) -> InterferometerReading:
        noise = self._rng.normal(0.0, self.noise.sigmas())
        return self._reading(self.geometry(), noise, self.clock.now())

    def average(self, duration_s: float) -> InterferometerReading:
        """Mean of the samples streamed over ``duration_s`` (advances the clock).

        While the machine and both units stand still the geometry is computed
        once and only the noise differs between samples.
        """
        n = max(1, round(duration_s * self.rate_hz))
        period_s = 1.0 / self.rate_hz
        if self._standstill():
            geometry = self.geometry()
            self.clock.sleep(n * period_s)
            noise = self._rng.normal(0.0, self.noise.sigmas(), (n, 6)).mean(axis=0)
            return self._reading(geometry, noise, self.clock.now())
        readings = []
        for _ in range(n):
            self.clock.sleep(period_s)
            readings.append(self.read())
        return mean_reading(readings)

    def _standstill(self) -> bool:
        return self.position.is_standstill() and self.launch.is_still() and self.receiver.is_still()
