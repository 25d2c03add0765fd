"""The simulated shop: air and material temperatures that drift during a calibration.

:class:`SimEnvironment` gives the true air temperature, pressure and humidity
and the machine's material temperature at any simulated time; the virtual
interferometer counts the optical path through that air and sees the machine
grow with its temperature. :class:`SimWeatherStation` reads it like an
XC-80-class station (air temperature, pressure, humidity, up to three material
sensors) with sensor noise, and can be told to fail a sensor or stop answering.
"""

from __future__ import annotations

import math
from contextlib import ExitStack
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from xmalign.environment import REFERENCE_TEMP_C, IndexMethod, air_index
from xmalign.errors import DeviceTimeoutError
from xmalign.geometry import Vec
from xmalign.roles import Clock, EnvironmentReading

if TYPE_CHECKING:
    from sim.world import World

#: Material sensors of the simulated station.
MATERIAL_SENSORS = 3


@dataclass(frozen=True)
class ShopClimate:
    """How the shop drifts from the start of the simulation (linear ramps plus a slow wave).

    Temperatures °C, pressure hPa, humidity %, times s.
    """

    air_start_c: float = 20.0
    air_end_c: float = 20.0
    pressure_start_hpa: float = 1013.25
    pressure_end_hpa: float = 1013.25
    humidity_start_percent: float = 50.0
    humidity_end_percent: float = 50.0
    material_start_c: float = 20.0
    material_end_c: float = 20.0
    #: Time over which the ramps run (they hold their end value afterwards).
    ramp_s: float = 3600.0
    #: Amplitude and period of a sine on the air temperature (air conditioning cycling).
    air_wave_c: float = 0.0
    air_wave_period_s: float = 900.0

    @classmethod
    def reference(cls) -> ShopClimate:
        """A shop held at 20 °C, 1013.25 hPa, 50 %."""
        return cls()

    @classmethod
    def drifting(cls, ramp_s: float = 1500.0) -> ShopClimate:
        """The benchmark's shop: air 22 -> 25 °C, the machine 22 -> 23 °C, pressure falling."""
        return cls(
            air_start_c=22.0,
            air_end_c=25.0,
            pressure_start_hpa=975.0,
            pressure_end_hpa=972.0,
            humidity_start_percent=45.0,
            humidity_end_percent=55.0,
            material_start_c=22.0,
            material_end_c=23.0,
            ramp_s=ramp_s,
            air_wave_c=0.2,
        )


#: The virtual shops a simulated run can have, by name (``--shop``).
SHOPS = {"drifting": ShopClimate.drifting, "reference": ShopClimate.reference}


def _ramp(start: float, end: float, fraction: float) -> float:
    return start + (end - start) * fraction


class SimEnvironment:
    """The true shop climate on a clock, and the machine's thermal growth.

    Parameters
    ----------
    clock : Clock
    climate : ShopClimate
    expansion_ppm_per_k : float
        Expansion coefficient of the machine's scales / structure.
    reference_mm : array_like, shape (3,)
        The CNC point that stays put when the machine grows (the scales' zero).
    method : str
        Refractive-index equation of the true air.
    """

    def __init__(
        self,
        clock: Clock,
        climate: ShopClimate | None = None,
        expansion_ppm_per_k: float = 0.0,
        reference_mm: ArrayLike = (0.0, 0.0, 0.0),
        method: IndexMethod = "edlen",
    ) -> None:
        self.clock = clock
        self.climate = climate or ShopClimate.reference()
        self.expansion_ppm_per_k = expansion_ppm_per_k
        self.reference_mm = np.asarray(reference_mm, dtype=float)
        self.method = method
        self._t0 = clock.now()

    def _fraction(self) -> float:
        elapsed = self.clock.now() - self._t0
        return min(max(elapsed / self.climate.ramp_s, 0.0), 1.0)

    def air_temp_c(self) -> float:
        c = self.climate
        wave = c.air_wave_c * math.sin(
            2 * math.pi * (self.clock.now() - self._t0) / c.air_wave_period_s
        )
        return _ramp(c.air_start_c, c.air_end_c, self._fraction()) + wave

    def air_pressure_hpa(self) -> float:
        c = self.climate
        return _ramp(c.pressure_start_hpa, c.pressure_end_hpa, self._fraction())

    def air_humidity_percent(self) -> float:
        c = self.climate
        return _ramp(c.humidity_start_percent, c.humidity_end_percent, self._fraction())

    def material_temp_c(self) -> float:
        c = self.climate
        return _ramp(c.material_start_c, c.material_end_c, self._fraction())

    def air_index(self) -> float:
        """Refractive index of the air now."""
        return float(
            air_index(
                self.air_temp_c(), self.air_pressure_hpa(), self.air_humidity_percent(), self.method
            )
        )

    def growth_mm(self, position_mm: ArrayLike) -> Vec:
        """How far the tool point at ``position_mm`` has moved by thermal growth, (3,)."""
        dt = self.material_temp_c() - REFERENCE_TEMP_C
        offset = np.asarray(position_mm, dtype=float) - self.reference_mm
        return self.expansion_ppm_per_k * 1e-6 * dt * offset


@dataclass
class SimWeatherStation:
    """``EnvironmentSource`` on a :class:`SimEnvironment`: an XC-80-class station.

    ``material_sensors`` sensors read the material temperature. Sensor noise is
    normal with the given standard deviations; ``failed`` holds names of
    sensors that report nothing (NaN); ``answering`` False makes :meth:`read`
    time out.
    """

    environment: SimEnvironment
    material_sensors: int = 1
    noise_temp_c: float = 0.01
    noise_pressure_hpa: float = 0.05
    noise_humidity_percent: float = 0.5
    seed: int | None = None
    failed: set[str] = field(default_factory=set)
    answering: bool = True

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng(self.seed)

    def _value(self, name: str, value: float, sigma: float) -> float:
        if name in self.failed:
            return math.nan
        return value + float(self._rng.normal(0.0, sigma)) if sigma > 0 else value

    def read(self) -> EnvironmentReading:
        if not self.answering:
            raise DeviceTimeoutError("simulated weather station: no answer")
        env = self.environment
        material = tuple(
            self._value(f"material_temp_c{k + 1}", env.material_temp_c(), self.noise_temp_c)
            for k in range(self.material_sensors)
        )
        return EnvironmentReading(
            time_s=env.clock.now(),
            air_temp_c=self._value("air_temp_c", env.air_temp_c(), self.noise_temp_c),
            air_pressure_hpa=self._value(
                "air_pressure_hpa", env.air_pressure_hpa(), self.noise_pressure_hpa
            ),
            air_humidity_percent=self._value(
                "air_humidity_percent", env.air_humidity_percent(), self.noise_humidity_percent
            ),
            material_temp_c=material,
        )


def attach_shop(world: World, climate: ShopClimate, seed: int | None = None) -> SimWeatherStation:
    """Give a world's interferometer the shop's air and thermal growth; its weather station.

    The machine grows about its travel's lower corner with its file's expansion coefficient.
    """
    machine = world.machine.machine
    environment = SimEnvironment(
        world.clock, climate, machine.thermal.expansion_ppm_per_k, machine.travel_min_mm
    )
    world.interferometer.environment = environment
    return SimWeatherStation(environment, material_sensors=MATERIAL_SENSORS, seed=seed)


def serve_station(world: World, servers: ExitStack) -> str:
    """Serve the world's weather station (a drifting shop) on a pty; the pty's path."""
    from sim.servers.weather_station import PtyStationServer

    server = PtyStationServer(attach_shop(world, ShopClimate.drifting()))
    server.start()
    servers.callback(server.stop)
    return server.port
