"""Air and material compensation of interferometer readings (pure numpy).

The refractive index of air follows the NIST Engineering Metrology Toolbox
("Index of Refraction of Air", J. A. Stone and J. H. Zimmerman, Appendix A):

- the modified Edlén equation: K. P. Birch and M. J. Downs, "An updated Edlén
  equation for the refractive index of air", Metrologia 30 (1993) 155-162, and
  "Correction to the updated Edlén equation ...", Metrologia 31 (1994) 315-316,
  with NIST's temperature factor ``292.75 / T`` on the water-vapour term;
- the Ciddor equation: P. E. Ciddor, "Refractive index of air: new equations
  for the visible and near infrared", Applied Optics 35 (1996) 1566-1573;
- the saturation vapour pressure over water of IAPWS (1997) and over ice of
  IAPWS (2008), as NIST uses them.

An interferometer counts the optical path with the vacuum wavelength of its
laser: its displacement reading ``D`` between its datum (beam length ``l0``,
index ``n0``) and now (``l``, ``n``) is ``n·l − n0·l0``. The geometric
displacement is therefore ``D / n + l0·(n0 − n) / n``: the first term divides
the reading by the index, the second is the *dead path* term, the change of the
optical length of the beam from the launch unit to the datum while the air
changes. Material normalisation to 20 °C (ISO 1) subtracts ``α·(T − 20)·L``.
docs/environment.md describes both with the reference values of the tests.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike

from xmalign.errors import InputError, TransportError
from xmalign.formats.measurements import MeasurementRow
from xmalign.formats.plan import Plan, PlanLine
from xmalign.geometry import Vec
from xmalign.roles import EnvironmentReading, EnvironmentSource

_log = logging.getLogger(__name__)

#: Vacuum wavelength of the HeNe laser of an XM-60-class interferometer, nm.
HENE_VACUUM_WAVELENGTH_NM = 632.991
#: ISO 1 reference temperature, °C.
REFERENCE_TEMP_C = 20.0
#: The environment columns of the measurement CSV (docs/formats.md), in this order.
ENVIRONMENT_COLUMNS = (
    "air_temp_c",
    "air_pressure_hpa",
    "air_humidity_percent",
    "material_temp_c",
)
#: What an XC-80-class station can report; a value outside is a sensor fault.
SENSOR_LIMITS: dict[str, tuple[float, float]] = {
    "air_temp_c": (-20.0, 60.0),
    "air_pressure_hpa": (600.0, 1100.0),
    "air_humidity_percent": (0.0, 100.0),
    "material_temp_c": (-20.0, 60.0),
}
IndexMethod = Literal["edlen", "ciddor"]

# IAPWS-IF97 saturation pressure over water (NIST Appendix A-I), T in K, result MPa
_K = (
    1.16705214528e03,
    -7.24213167032e05,
    -1.70738469401e01,
    1.20208247025e04,
    -3.23255503223e06,
    1.49151086135e01,
    -4.82326573616e03,
    4.05113405421e05,
    -2.38555575678e-01,
    6.50175348448e02,
)
# IAPWS 2008 sublimation pressure over ice
_ICE_A1, _ICE_A2, _TRIPLE_K, _TRIPLE_PA = -13.928169, 34.7078238, 273.16, 611.657


def saturation_vapour_pressure_pa(air_temp_c: ArrayLike) -> Vec:
    """Saturation vapour pressure of water (over ice below 0 °C), Pa, shape of the input."""
    t = np.asarray(air_temp_c, dtype=float)
    kelvin = t + 273.15
    omega = kelvin + _K[8] / (kelvin - _K[9])
    a = omega**2 + _K[0] * omega + _K[1]
    b = _K[2] * omega**2 + _K[3] * omega + _K[4]
    c = _K[5] * omega**2 + _K[6] * omega + _K[7]
    x = -b + np.sqrt(b**2 - 4 * a * c)
    water = 1e6 * (2 * c / x) ** 4
    theta = kelvin / _TRIPLE_K
    ice = _TRIPLE_PA * np.exp(_ICE_A1 * (1 - theta**-1.5) + _ICE_A2 * (1 - theta**-1.25))
    return np.where(t >= 0.0, water, ice)


def _wavenumber_sq(wavelength_nm: float) -> float:
    """``S = 1/λ²`` with λ the vacuum wavelength in µm."""
    return 1.0 / (wavelength_nm * 1e-3) ** 2


def edlen_index(
    air_temp_c: ArrayLike,
    air_pressure_hpa: ArrayLike,
    air_humidity_percent: ArrayLike,
    wavelength_nm: float = HENE_VACUUM_WAVELENGTH_NM,
) -> Vec:
    """Refractive index of air, modified Edlén (Birch & Downs 1993/1994, NIST), broadcast shape.

    Standard air with 450 ppm CO2.
    """
    t = np.asarray(air_temp_c, dtype=float)
    p = np.asarray(air_pressure_hpa, dtype=float) * 100.0
    s = _wavenumber_sq(wavelength_nm)
    vapour_pa = np.asarray(air_humidity_percent, dtype=float) / 100.0
    vapour_pa = vapour_pa * saturation_vapour_pressure_pa(t)
    standard = 1e-8 * (8342.54 + 2406147.0 / (130.0 - s) + 15998.0 / (38.9 - s))
    density = (1 + 1e-8 * (0.601 - 0.00972 * t) * p) / (1 + 0.003661 * t)
    dry = p * standard * density / 96095.43
    water = 1e-10 * (292.75 / (t + 273.15)) * (3.7345 - 0.0401 * s) * vapour_pa
    return 1.0 + dry - water


_R_GAS = 8.314472
_M_WATER = 0.018015


def ciddor_index(
    air_temp_c: ArrayLike,
    air_pressure_hpa: ArrayLike,
    air_humidity_percent: ArrayLike,
    wavelength_nm: float = HENE_VACUUM_WAVELENGTH_NM,
    co2_ppm: float = 450.0,
) -> Vec:
    """Refractive index of air, Ciddor (1996) as in NIST Appendix A-III, broadcast shape."""
    t = np.asarray(air_temp_c, dtype=float)
    p = np.asarray(air_pressure_hpa, dtype=float) * 100.0
    kelvin = t + 273.15
    s = _wavenumber_sq(wavelength_nm)
    enhancement = 1.00062 + 3.14e-8 * p + 5.6e-7 * t**2
    xv = np.asarray(air_humidity_percent, dtype=float) / 100.0
    xv = xv * enhancement * saturation_vapour_pressure_pa(t) / p
    r_air = 1e-8 * (5792105.0 / (238.0185 - s) + 167917.0 / (57.362 - s))
    r_air = r_air * (1 + 5.34e-7 * (co2_ppm - 450.0))
    r_water = 1.022e-8 * (295.235 + 2.6422 * s - 0.032380 * s**2 + 0.004028 * s**3)
    molar_air = 0.0289635 + 1.2011e-8 * (co2_ppm - 400.0)
    z = (
        1
        - (p / kelvin)
        * (
            1.58123e-6
            - 2.9331e-8 * t
            + 1.1043e-10 * t**2
            + (5.707e-6 - 2.051e-8 * t) * xv
            + (1.9898e-4 - 2.376e-6 * t) * xv**2
        )
        + (p / kelvin) ** 2 * (1.83e-11 - 0.765e-8 * xv**2)
    )
    rho_air_standard = 101325.0 * molar_air / (0.9995922115 * _R_GAS * 288.15)
    rho_water_standard = 0.00985938
    rho_air = (1 - xv) * p * molar_air / (z * _R_GAS * kelvin)
    rho_water = xv * p * _M_WATER / (z * _R_GAS * kelvin)
    return 1.0 + rho_air / rho_air_standard * r_air + rho_water / rho_water_standard * r_water


def air_index(
    air_temp_c: ArrayLike,
    air_pressure_hpa: ArrayLike,
    air_humidity_percent: ArrayLike,
    method: IndexMethod = "edlen",
    wavelength_nm: float = HENE_VACUUM_WAVELENGTH_NM,
) -> Vec:
    """Refractive index of air by ``method`` (``edlen`` or ``ciddor``)."""
    if method == "edlen":
        return edlen_index(air_temp_c, air_pressure_hpa, air_humidity_percent, wavelength_nm)
    if method == "ciddor":
        return ciddor_index(air_temp_c, air_pressure_hpa, air_humidity_percent, wavelength_nm)
    raise InputError(f"refractive index method '{method}': expected edlen or ciddor")


def out_of_range(name: str, values: ArrayLike) -> np.ndarray:
    """True where a sensor value is not finite or outside what the sensor can report."""
    low, high = SENSOR_LIMITS[name]
    v = np.asarray(values, dtype=float)
    with np.errstate(invalid="ignore"):
        return ~np.isfinite(v) | (v < low) | (v > high)


def check_sensor(name: str, value: float, source: str) -> float:
    """The value if the sensor can report it, else InputError naming ``source`` and the sensor."""
    if out_of_range(name, value):
        low, high = SENSOR_LIMITS[name]
        raise InputError(
            f"{source}: {name} {value:g} is outside what the sensor can report"
            f" ({low:g} to {high:g})"
        )
    return float(value)


@dataclass(frozen=True)
class EnvironmentColumns:
    """The environment of every measured point, shape (N,) each; None where not measured."""

    air_temp_c: Vec | None = None
    air_pressure_hpa: Vec | None = None
    air_humidity_percent: Vec | None = None
    material_temp_c: Vec | None = None

    @property
    def has_air(self) -> bool:
        air = (self.air_temp_c, self.air_pressure_hpa, self.air_humidity_percent)
        return all(c is not None for c in air)

    @property
    def has_material(self) -> bool:
        return self.material_temp_c is not None

    def column(self, name: str) -> Vec | None:
        return getattr(self, name)

    def index(self, method: IndexMethod = "edlen") -> Vec:
        """Refractive index at every point, (N,); raises InputError without the air columns."""
        temp_c, pressure_hpa, humidity = (
            self.air_temp_c,
            self.air_pressure_hpa,
            self.air_humidity_percent,
        )
        if temp_c is None or pressure_hpa is None or humidity is None:
            raise InputError("no air temperature, pressure and humidity to compute the index from")
        return air_index(temp_c, pressure_hpa, humidity, method)

    def take(self, rows: np.ndarray) -> EnvironmentColumns:
        """The columns of some rows (boolean mask or indices)."""
        return EnvironmentColumns(
            *(None if (c := self.column(n)) is None else c[rows] for n in ENVIRONMENT_COLUMNS)
        )


def datum_rows(run: ArrayLike, sign: ArrayLike, index: ArrayLike) -> np.ndarray:
    """For every row, the row of its run's datum (the ``+`` pass's first target), (N,) int.

    A run without that row (resumed after it, or damaged) takes its first row.
    """
    run, sign, index = (np.asarray(a) for a in (run, sign, index))
    datum = np.empty(len(run), dtype=int)
    for r in np.unique(run):
        members = np.flatnonzero(run == r)
        first = members[(sign[members] > 0) & (index[members] == 0)]
        datum[members] = first[0] if len(first) else members[0]
    return datum


def dead_path_um(dead_path_mm: float, index: Vec, datum_index: Vec) -> Vec:
    """Change of the beam length that the dead path fakes, um: ``l0·(n0 − n)/n``, (N,)."""
    return dead_path_mm * 1e3 * (datum_index - index) / index


def material_um(displacement_mm: ArrayLike, material_temp_c: ArrayLike, ppm_per_k: float) -> Vec:
    """Thermal expansion ``α·(T − 20)·L`` over the displacement, um, broadcast shape."""
    dt = np.asarray(material_temp_c, dtype=float) - REFERENCE_TEMP_C
    return ppm_per_k * 1e-3 * dt * np.asarray(displacement_mm, dtype=float)


@dataclass(frozen=True)
class Compensation:
    """Result of :func:`compensate_linear`.

    Attributes
    ----------
    linear_um : ndarray, shape (N,)
        Compensated positional deviation, um.
    index : ndarray, shape (N,)
        Refractive index used at every point (1 where air was not compensated).
    air, material : bool
        Whether the air and the material were compensated.
    dead_path_um : ndarray, shape (N,)
        Dead-path term added, um.
    """

    linear_um: Vec
    index: Vec
    air: bool
    material: bool
    dead_path_um: Vec

    @property
    def note(self) -> str:
        """One sentence for the report."""
        parts = []
        parts.append(
            "air compensated (modified Edlén), dead path included"
            if self.air
            else "no air data: readings taken as already air-compensated"
        )
        parts.append(
            "normalised to 20 °C from the material temperature"
            if self.material
            else "no material temperature: readings taken as at 20 °C"
        )
        return "; ".join(parts)


def compensate_linear(
    linear_um: ArrayLike,
    displacement_mm: ArrayLike,
    datum: ArrayLike,
    environment: EnvironmentColumns,
    expansion_ppm_per_k: float,
    dead_path_mm: float = 0.0,
    beam_sign: float = 1.0,
    method: IndexMethod = "edlen",
) -> Compensation:
    """Compensate the linear channel of one line for the air and the material.

    Parameters
    ----------
    linear_um : array_like, shape (N,)
        The CSV's ``linear_um``: measured minus commanded displacement, the
        measured one counted in vacuum wavelengths (optical path).
    displacement_mm : array_like, shape (N,)
        Commanded displacement from the run's first point, ``L``.
    datum : array_like of int, shape (N,)
        Row of each row's datum (:func:`datum_rows`).
    environment : EnvironmentColumns
        Columns of the same rows; missing columns are not compensated.
    expansion_ppm_per_k : float
        The machine file's ``thermal.expansion_ppm_per_k``.
    dead_path_mm : float
        Beam length from the launch unit to the line's first point (the plan's
        ``beam_distance_mm[0]``).
    beam_sign : float
        +1 when the receiver moves away from the launch unit along the line, -1 towards it.
    """
    linear = np.asarray(linear_um, dtype=float)
    length_um = np.asarray(displacement_mm, dtype=float) * 1e3
    datum = np.asarray(datum, dtype=int)
    index = np.ones_like(linear)
    dead = np.zeros_like(linear)
    if environment.has_air:
        index = environment.index(method)
        dead = beam_sign * dead_path_um(dead_path_mm, index, index[datum])
        linear = (linear + length_um) / index - length_um + dead
    material_temp_c = environment.material_temp_c
    if material_temp_c is not None and expansion_ppm_per_k != 0.0:
        linear = linear - material_um(length_um * 1e-3, material_temp_c, expansion_ppm_per_k)
    return Compensation(linear, index, environment.has_air, environment.has_material, dead)


def compensate_line(
    line: PlanLine,
    run: ArrayLike,
    sign: ArrayLike,
    index: ArrayLike,
    linear_um: ArrayLike,
    environment: EnvironmentColumns,
    expansion_ppm_per_k: float,
    method: IndexMethod = "edlen",
) -> Compensation:
    """:func:`compensate_linear` for the rows (N,) of one plan line.

    The commanded displacement, the datum of each run and the dead path come
    from the plan line (``targets_mm``, ``beam_distance_mm``).
    """
    index = np.asarray(index, dtype=int)
    displacement = line.targets_mm[index] - line.targets_mm[0]
    dead_path, beam_sign = beam_geometry(line.extra.get("beam_distance_mm"))
    return compensate_linear(
        linear_um,
        displacement,
        datum_rows(run, sign, index),
        environment,
        expansion_ppm_per_k,
        dead_path,
        beam_sign,
        method,
    )


def beam_geometry(beam_distance_mm: Sequence[float] | None) -> tuple[float, float]:
    """Dead path (mm) and beam sign from a plan line's ``beam_distance_mm`` [first, last].

    Without it (an older plan) the dead path is 0 and the receiver taken to move away.
    """
    if beam_distance_mm is None or len(beam_distance_mm) < 2:
        return 0.0, 1.0
    first, last = (float(v) for v in beam_distance_mm)
    return first, 1.0 if last >= first else -1.0


@dataclass(frozen=True)
class Range:
    """Minimum, mean and maximum of one quantity (NaN when there is none)."""

    min: float
    mean: float
    max: float

    @classmethod
    def of(cls, values: Vec | None) -> Range:
        if values is None or len(values) == 0:
            return cls(math.nan, math.nan, math.nan)
        v = np.asarray(values, dtype=float)
        return cls(float(v.min()), float(v.mean()), float(v.max()))


def summarise(environment: EnvironmentColumns) -> dict[str, Range]:
    """Minimum, mean and maximum of every column, by column name."""
    return {name: Range.of(environment.column(name)) for name in ENVIRONMENT_COLUMNS}


@dataclass(frozen=True)
class DriftCheck:
    """Drift of one line: the first target re-measured at the end minus its datum, um."""

    line_id: str
    drift_um: float
    limit_um: float | None

    @property
    def exceeded(self) -> bool:
        return self.limit_um is not None and abs(self.drift_um) > self.limit_um

    def message(self) -> str:
        text = f"line {self.line_id}: drift {self.drift_um:+.2f} um at the first target"
        if self.exceeded:
            text += f" exceeds the machine file's limit {self.limit_um:g} um"
        return text


def line_drift(
    line_id: str, remeasured_um: ArrayLike, datum_um: float = 0.0, limit_um: float | None = None
) -> DriftCheck:
    """Drift of a line from its compensated re-measurement(s) of the first target, um.

    ``remeasured_um`` are the compensated ``linear_um`` of the re-measurement
    (relative to the last run's datum, where the reading is ``datum_um``,
    normally 0); their mean minus ``datum_um`` is the drift.
    """
    values = np.atleast_1d(np.asarray(remeasured_um, dtype=float))
    if values.size == 0:
        raise InputError(f"line {line_id}: no re-measurement of the first target")
    return DriftCheck(line_id, float(values.mean() - datum_um), limit_um)


@dataclass(frozen=True)
class EnvironmentSample:
    """The environment columns of one captured point and what was wrong with them.

    ``values`` maps column names of :data:`ENVIRONMENT_COLUMNS` present in the
    run to values; ``flags`` names every value that was held at its last good
    reading, and why (empty when all were fresh).
    """

    values: dict[str, float]
    flags: tuple[str, ...] = ()

    @property
    def flag_text(self) -> str:
        """The flags as one CSV field (``;``-separated)."""
        return "; ".join(self.flags)


def _columns_of(reading: EnvironmentReading) -> dict[str, float]:
    values = {
        "air_temp_c": reading.air_temp_c,
        "air_pressure_hpa": reading.air_pressure_hpa,
        "air_humidity_percent": reading.air_humidity_percent,
    }
    if reading.material_temp_c:
        material = np.asarray(reading.material_temp_c, dtype=float)
        good = material[~out_of_range("material_temp_c", material)]
        values["material_temp_c"] = float(good.mean()) if len(good) else math.nan
    return values


class EnvironmentMonitor:
    """Samples an ``EnvironmentSource`` for every captured point; never loses a point.

    :meth:`prime` takes the first reading before the run starts: it must be
    complete and in range, else a one-line error. Afterwards a sensor that
    reports nothing or a value it cannot report, or a station that stops
    answering, keeps the last good value in the row and flags it.
    """

    def __init__(self, source: EnvironmentSource, name: str = "weather station") -> None:
        self.source = source
        self.name = name
        self._last: dict[str, float] = {}
        self._warned: set[str] = set()

    @property
    def columns(self) -> tuple[str, ...]:
        """The columns this run writes (known after :meth:`prime`)."""
        return tuple(name for name in ENVIRONMENT_COLUMNS if name in self._last)

    def prime(self) -> EnvironmentSample:
        """First reading; raises InputError naming the sensor when it is incomplete."""
        try:
            reading = self.source.read()
        except TransportError as error:
            raise type(error)(f"{self.name}: {error}") from error
        values = _columns_of(reading)
        for name, value in values.items():
            if math.isnan(value):
                raise InputError(f"{self.name}: no reading from the {name} sensor")
            check_sensor(name, value, self.name)
        self._last = dict(values)
        return EnvironmentSample(dict(values))

    def sample(self) -> EnvironmentSample:
        """The environment now; held values are flagged (and logged once per cause)."""
        if not self._last:
            return self.prime()
        try:
            values = _columns_of(self.source.read())
        except TransportError as error:
            reason = f"{self.name} not answering ({error})"
            return EnvironmentSample(
                dict(self._last),
                tuple(self._flag(name, reason, "station") for name in self.columns),
            )
        flags = []
        for name in self.columns:
            value = values.get(name, math.nan)
            if math.isnan(value):
                flags.append(self._flag(name, "no reading", "missing"))
            elif out_of_range(name, value):
                flags.append(self._flag(name, f"{value:g} out of the sensor's range", "range"))
            else:
                self._last[name] = value
        return EnvironmentSample(dict(self._last), tuple(flags))

    def _flag(self, name: str, reason: str, cause: str) -> str:
        """The flag text; logged the first time ``name`` is held for ``cause``."""
        text = f"{name} held: {reason}"
        if f"{name}/{cause}" not in self._warned:
            self._warned.add(f"{name}/{cause}")
            _log.warning("%s: %s; rows keep the last good value, flagged", self.name, text)
        return text


#: ``run`` of the row that re-measures a line's first target after its last run (drift check).
DRIFT_RUN = 0


@dataclass
class StationCompensation:
    """What :func:`compensate_station` did to one station's measurement.

    Attributes
    ----------
    rows : list of MeasurementRow
        The rows with ``linear_um`` compensated, drift-check rows removed.
    lines : dict of str to Compensation
        Per line id.
    environment : dict of str to dict of str to Range
        Per line id, min / mean / max of every environment column.
    drift : list of DriftCheck
        Lines that have a drift-check row.
    """

    rows: list[MeasurementRow]
    lines: dict[str, Compensation]
    environment: dict[str, dict[str, Range]]
    drift: list[DriftCheck]

    @property
    def note(self) -> str:
        """How the readings were treated (the first line's note; all lines share the columns)."""
        return next(iter(self.lines.values())).note if self.lines else ""


def _columns(environments: Sequence[Mapping[str, float]]) -> EnvironmentColumns:
    present = [name for name in ENVIRONMENT_COLUMNS if environments and name in environments[0]]
    return EnvironmentColumns(
        **{name: np.array([float(e[name]) for e in environments]) for name in present}
    )


def compensate_station(
    plan: Plan,
    rows: Sequence[MeasurementRow],
    environments: Sequence[Mapping[str, float]],
    expansion_ppm_per_k: float,
    drift_limit_um: float | None = None,
    method: IndexMethod = "edlen",
) -> StationCompensation:
    """Compensate the rows of one plan (a station) for air, dead path and material.

    ``environments`` gives each row's environment columns (an empty mapping
    when the file has none). A row with ``run`` :data:`DRIFT_RUN` re-measures
    the line's first target after the last run, relative to that run's datum:
    its compensated reading is the line's drift, checked against ``drift_limit_um``.
    """
    out: list[MeasurementRow] = []
    lines: dict[str, Compensation] = {}
    summaries: dict[str, dict[str, Range]] = {}
    drift: list[DriftCheck] = []
    for line in plan.lines:
        members = [k for k, row in enumerate(rows) if row.line == line.id]
        if not members:
            continue
        line_rows = [rows[k] for k in members]
        environment = _columns([environments[k] for k in members])
        run = np.array([r.run for r in line_rows])
        last = run[run != DRIFT_RUN].max(initial=1)
        result = compensate_line(
            line,
            np.where(run == DRIFT_RUN, last, run),
            [1.0 if r.direction == "+" else -1.0 for r in line_rows],
            [r.index for r in line_rows],
            [r.channels[0] for r in line_rows],
            environment,
            expansion_ppm_per_k,
            method,
        )
        check = run == DRIFT_RUN
        if check.any():
            drift.append(line_drift(line.id, result.linear_um[check], 0.0, drift_limit_um))
        for row, linear, is_check in zip(line_rows, result.linear_um, check, strict=True):
            if not is_check:
                channels = row.channels.copy()
                channels[0] = linear
                out.append(replace(row, channels=channels))
        lines[line.id] = result
        summaries[line.id] = summarise(environment.take(~check))
    # rows of lines the plan does not have are left for the caller to refuse
    planned = {line.id for line in plan.lines}
    out.extend(row for row in rows if row.line not in planned)
    return StationCompensation(out, lines, summaries, drift)


@dataclass(frozen=True)
class SensorUncertainty:
    """Standard uncertainties (k = 1) behind the environment compensation.

    Defaults: XC-80-class sensor accuracies (air ±0.2 °C, ±1 hPa, ±6 %,
    material ±0.1 °C) taken as rectangular distributions, 10 % of the
    expansion coefficient, and 1.5e-8 for the refractive-index equation itself.
    """

    air_temp_c: float = 0.2 / math.sqrt(3)
    air_pressure_hpa: float = 1.0 / math.sqrt(3)
    air_humidity_percent: float = 6.0 / math.sqrt(3)
    material_temp_c: float = 0.1 / math.sqrt(3)
    expansion_relative: float = 0.1
    index_equation: float = 1.5e-8


def index_uncertainty(
    air_temp_c: float,
    air_pressure_hpa: float,
    air_humidity_percent: float,
    sensors: SensorUncertainty | None = None,
) -> float:
    """Standard uncertainty of the refractive index from the sensors and the equation."""
    u = sensors or SensorUncertainty()
    point = np.array([air_temp_c, air_pressure_hpa, air_humidity_percent], dtype=float)
    steps = np.array([u.air_temp_c, u.air_pressure_hpa, u.air_humidity_percent])
    terms = [u.index_equation]
    for k, step in enumerate(steps):
        shifted = point.copy()
        shifted[k] += step
        terms.append(float(edlen_index(*shifted) - edlen_index(*point)))
    return float(np.sqrt(np.sum(np.square(terms))))


def linear_budget_um(
    length_mm: float,
    environment: Mapping[str, Range],
    expansion_ppm_per_k: float,
    sensors: SensorUncertainty | None = None,
) -> dict[str, float]:
    """Standard uncertainties (k = 1, um) the environment adds to a positioning error at ``L``.

    ``environment`` holds the measured ranges (:func:`summarise`); a quantity
    without data contributes nothing (the readings were taken as compensated).
    """
    u = sensors or SensorUncertainty()
    out: dict[str, float] = {}
    air = [r.mean for n in ENVIRONMENT_COLUMNS[:3] if (r := environment.get(n)) is not None]
    if len(air) == 3 and all(math.isfinite(mean) for mean in air):
        n_u = index_uncertainty(air[0], air[1], air[2], u)
        out["air refractive index"] = n_u * length_mm * 1e3
    material = environment.get("material_temp_c")
    if material is not None and math.isfinite(material.mean) and expansion_ppm_per_k:
        alpha = expansion_ppm_per_k * 1e-3  # um per mm and K
        out["material temperature"] = alpha * u.material_temp_c * length_mm
        dt = abs(material.mean - REFERENCE_TEMP_C)
        out["expansion coefficient"] = alpha * u.expansion_relative * dt * length_mm
    return out
