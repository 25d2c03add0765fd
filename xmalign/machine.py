"""The machine description (YAML) of docs/formats.md, validated with pydantic.

Besides the keys of the spec, two optional sections are xmalign's own
(documented in docs/conventions-notes.md): ``uncertainty`` (the a-priori
uncertainties identification and planning use) and ``measurement`` (target
spacing, runs, dwell and stand-off for ``xmalign program``). Every number
must be finite and within what a real machine can have (docs/formats.md,
"Validation").
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, PrivateAttr, field_validator, model_validator

from xmalign.errors import InputError
from xmalign.formats.common import (
    MAX_LENGTH_MM,
    Angle_deg,
    Distance_mm,
    StrictFileModel,
    Vector3_mm,
    format_problem,
    located,
    path_argument,
    read_yaml,
    validate,
)
from xmalign.formats.provenance import FileSource
from xmalign.geometry import Vec

AxisName = Literal["X", "Y", "Z"]
AXES: tuple[AxisName, AxisName, AxisName] = ("X", "Y", "Z")
CONTROLLERS = ("sinumerik", "fanuc", "heidenhain", "linuxcnc", "isg")
#: The machine file's format; ``format:`` is optional (absent: version 1).
MACHINE_FORMAT = "xmalign.machine/1"
#: The series of each controller family xmalign knows (``cnc.series``); the first is the
#: default, said in every file the writer makes (docs/controllers.md).
SERIES: dict[str, tuple[str, ...]] = {
    "sinumerik": ("840D sl", "828D", "ONE"),
    "fanuc": ("0i", "16i", "18i", "30i", "31i", "32i"),
    "heidenhain": ("MANUALplus 620", "TNC 620", "TNC 640", "TNC 4xx", "iTNC 530"),
    "linuxcnc": ("2.9",),
    "isg": ("ISG kernel",),
}
Direction = Literal["+", "-"]

Vector3 = Vector3_mm
TravelRange = Annotated[
    list[Annotated[float, Field(ge=-MAX_LENGTH_MM, le=MAX_LENGTH_MM)]],
    Field(min_length=2, max_length=2),
]
#: Feeds up to 500 m/min; micrometres up to 10 mm; microradians up to 0.1 rad.
Feed_mm_min = Annotated[float, Field(gt=0, le=500_000, allow_inf_nan=False)]
#: Largest a-priori standard uncertainty of a length (10 mm) and of an angle (0.1 rad).
MAX_UNCERTAINTY_UM = 10_000.0
MAX_UNCERTAINTY_URAD = 100_000.0
Micrometres = Annotated[float, Field(gt=0, le=MAX_UNCERTAINTY_UM, allow_inf_nan=False)]
Microradians = Annotated[float, Field(gt=0, le=MAX_UNCERTAINTY_URAD, allow_inf_nan=False)]
Allowance_um = Annotated[float, Field(ge=0, le=10_000, allow_inf_nan=False)]
Allowance_urad = Annotated[float, Field(ge=0, le=100_000, allow_inf_nan=False)]
Allowance_ppm = Annotated[float, Field(ge=0, le=1000, allow_inf_nan=False)]
SmrName = Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")]
Expansion_ppm_per_k = Annotated[float, Field(ge=-5.0, le=50.0, allow_inf_nan=False)]
Spacing_mm = Annotated[float, Field(gt=0, le=200, allow_inf_nan=False)]
Seconds = Annotated[float, Field(ge=0, le=3600, allow_inf_nan=False)]
Overrun_mm = Annotated[float, Field(ge=0, le=1000, allow_inf_nan=False)]
NonNegativeLength_mm = Annotated[float, Field(ge=0, le=MAX_LENGTH_MM, allow_inf_nan=False)]
_Strict = StrictFileModel


class Feeds(_Strict):
    rapid: Feed_mm_min
    measure: Feed_mm_min


class LaunchUnitGuess(_Strict):
    position_mm: Vector3


class InterferometerRanges(_Strict):
    max_range_mm: Distance_mm = 4000.0
    straightness_range_um: Micrometres = 250.0
    angle_range_urad: Microradians = 500.0
    #: xmalign's own: the fastest the interferometer tracks the receiver, mm/min
    #: (``program`` moves between targets no faster; None: the rapid feed).
    max_speed_mm_min: Feed_mm_min | None = None
    #: xmalign's own: how far off the receiver's centre the beam still gives a signal
    #: (beam present, any strength), mm; sizes the search for the first alignment.
    capture_radius_mm: Annotated[float, Field(gt=0, le=50, allow_inf_nan=False)] = 6.0
    #: xmalign's own: how far the receiver may face away from the beam and still see
    #: it, mrad (the same search).
    capture_angle_mrad: Annotated[float, Field(gt=0, le=500, allow_inf_nan=False)] = 35.0

    def ranges(self) -> dict[str, float]:
        """The three ranges by name (the arguments of ``ChannelLimits.of_ranges``)."""
        return self.model_dump(
            include={"max_range_mm", "straightness_range_um", "angle_range_urad"}
        )

    def channel_limits(self) -> Vec:
        """The largest credible reading of each channel (roles.CHANNELS order), shape (6,).

        Twice the instrument's ranges (um, urad): a reading beyond is a
        corrupted value, not a measurement.
        """
        return 2.0 * np.array(
            [1000.0 * self.max_range_mm, *[self.straightness_range_um] * 2]
            + [self.angle_range_urad] * 3
        )


class Thermal(_Strict):
    """Normalisation of linear errors to 20 °C: the expansion of the machine's scales."""

    expansion_ppm_per_k: Expansion_ppm_per_k = 0.0
    #: xmalign's own: warn when a line's first target drifts more than this, um.
    drift_limit_um: Micrometres | None = None


class Uncertainty(_Strict):
    """Standard uncertainties (k = 1) of what identification is built from."""

    encoder_urad: Microradians = 10.0
    machine_position_um: Micrometres = 20.0
    unit_kinematics_um: Micrometres = 10.0
    encoder_zero_offset_urad: Microradians = 100.0
    distance_um: Micrometres = 20.0
    straightness_um: Micrometres = 2.0
    # the machine's own errors at the identification positions (docs/identification.md)
    tool_rotation_urad: Microradians = 15.0
    tool_rotation_common_urad: Microradians = 18.0
    machine_common_um: Micrometres = 15.0
    beam_collimation_urad: Microradians = 20.0
    # interferometer channels, used by ``xmalign post`` to weight and propagate (GUM)
    channel_linear_um: Micrometres = 0.5
    channel_straightness_um: Micrometres = 1.0
    channel_angle_urad: Microradians = 1.0
    channel_roll_urad: Microradians = 2.5


#: Uncertainty model ``[a_um, b_um_per_m]``: a + b per metre of distance (k = 1).
DistanceModel_um = Annotated[
    list[Annotated[float, Field(ge=0, le=10_000, allow_inf_nan=False)]],
    Field(min_length=2, max_length=2),
]


class TrackerUncertainty(_Strict):
    """Standard uncertainty (k = 1) of one laser-tracker point, along and across the beam.

    Defaults: half the maximum permissible errors a tracker maker publishes
    (distance 10 um + 0.3 um/m, transverse 15 um + 6 um/m; docs/formats.md).
    """

    radial_um: DistanceModel_um = [5.0, 0.15]
    transverse_um: DistanceModel_um = [7.5, 3.0]
    #: RMS over all directions of the angle errors common to every run at a station
    #: (docs/formats.md "Systematic instrument errors"); 0: none
    angle_systematic_urad: Allowance_urad = 0.0
    #: standard uncertainty of one scale factor per station and run (air compensation)
    scale_ppm: Allowance_ppm = 0.0

    def radial_sigma_mm(self, distance_mm: Vec) -> Vec:
        """Standard uncertainty along the beam at distances (N,), mm."""
        return _affine_mm(self.radial_um, distance_mm)

    def transverse_sigma_mm(self, distance_mm: Vec) -> Vec:
        """Standard uncertainty across the beam at distances (N,), mm."""
        return _affine_mm(self.transverse_um, distance_mm)


class TracerUncertainty(_Strict):
    """Standard uncertainty (k = 1) of one laser-tracer length (default 0.1 um + 0.15 um/m)."""

    length_um: DistanceModel_um = [0.1, 0.15]
    #: standard uncertainty of one scale factor per place and run (air compensation)
    scale_ppm: Allowance_ppm = 0.0

    def length_sigma_mm(self, length_mm: Vec) -> Vec:
        """Standard uncertainty of lengths (N,), mm."""
        return _affine_mm(self.length_um, length_mm)


def _affine_mm(model_um: list[float], distance_mm: Vec) -> Vec:
    a, b = model_um
    sigma = (a + b * np.abs(np.asarray(distance_mm, dtype=float)) / 1000.0) * 1e-3
    # a model of 0 + 0 would give infinite weights; 1 nm is below any instrument
    return np.maximum(sigma, 1e-6)


class Measurement(_Strict):
    """How ``xmalign program`` lays out the measuring lines."""

    target_spacing_mm: Spacing_mm = 100.0
    #: runs of the axis lines X, Y, Z (repeatability, ISO 230-2 statistics)
    runs: Annotated[int, Field(ge=1, le=5)] = 2
    #: runs of the face diagonals XY, YZ, XZ (docs/machine-time.md)
    diagonal_runs: Annotated[int, Field(ge=1, le=5)] = 2
    bidirectional: bool = True
    dwell_s: Seconds = 0.5
    overrun_mm: Overrun_mm = 5.0
    #: each target is approached at the measuring feed over this last distance only
    approach_mm: Overrun_mm = 2.0
    standoff_mm: NonNegativeLength_mm = 150.0
    irregular_spacing: bool = False
    min_line_mm: Distance_mm = 100.0
    straightness_allowance_um: Allowance_um = 50.0
    angle_allowance_urad: Allowance_urad = 100.0


class WorkOffset(_Strict):
    """A work offset the programs run in: ``code`` (G54 .. G59) and its origin in machine mm."""

    code: Literal["G54", "G55", "G56", "G57", "G58", "G59"]
    origin_mm: Vector3

    @property
    def number(self) -> int:
        """1 for G54 .. 6 for G59 (the ``P`` of ``G10 L2``)."""
        return int(self.code[1:]) - 53


class Cnc(_Strict):
    """How programs and compensation tables meet the controller (xmalign's own, optional).

    See docs/controllers.md. Lengths in mm, machine (joint) coordinates.
    """

    work_offset: WorkOffset | None = None
    tool_offset_mm: Vector3 = [0.0, 0.0, 0.0]
    reference_mm: Vector3 = [0.0, 0.0, 0.0]
    joints: Annotated[list[AxisName], Field(min_length=3, max_length=9)] | None = None
    axis_names: dict[AxisName, Annotated[str, Field(pattern=r"^[A-Z][A-Z0-9_]{0,15}$")]] = {}
    detection_unit_um: Annotated[float, Field(gt=0, le=10)] = 1.0
    #: largest correction the LinuxCNC volumetric component applies before it faults
    max_correction_um: Micrometres = 100.0
    #: path acceleration and deceleration, mm/s² (machine-time estimate and simulator)
    acceleration_mm_s2: Annotated[float, Field(gt=0, le=100_000, allow_inf_nan=False)] | None = None
    #: the controller's series within its family (``SERIES``; default: the first)
    series: str | None = None
    #: direction in which each axis makes its reference return (default: from where
    #: ``reference_mm`` lies in the travel, see :meth:`Machine.reference_return`)
    reference_return: dict[AxisName, Direction] = {}
    #: the controller's own backlash compensation of each axis, um, where known
    backlash_um: dict[AxisName, Allowance_um] = {}

    @field_validator("joints")
    @classmethod
    def _joints_cover_xyz(cls, joints: list[str] | None) -> list[str] | None:
        if joints is not None and set(joints) != set(AXES):
            raise ValueError(f"{joints} must give X, Y and Z at least one joint each")
        return joints

    @property
    def tool_offset(self) -> Vec:
        """Tool point offset ``t`` for the compensation fit, mm, shape (3,)."""
        return np.asarray(self.tool_offset_mm, dtype=float)

    @property
    def reference(self) -> Vec:
        """Reference point of each axis (where tables are zero), mm, shape (3,)."""
        return np.asarray(self.reference_mm, dtype=float)

    def axis_name(self, axis: str, default: str) -> str:
        """The controller's name of ``axis`` (``default`` when the file gives none)."""
        return next((name for key, name in self.axis_names.items() if key == axis), default)

    def backlash(self, axis: str) -> float | None:
        """The controller's own backlash compensation of ``axis``, um (None: not given)."""
        return next((um for key, um in self.backlash_um.items() if key == axis), None)


class Machine(_Strict):
    """A machine tool as xmalign sees it; lengths mm, angles as named.

    ``format`` (optional, :data:`MACHINE_FORMAT`): a file without it is version 1.
    :attr:`source` is the file it was read from (path and SHA-256 of its bytes as
    read), None for a machine made in code or changed since (``model_copy(update=)``).
    """

    format: str | None = None
    name: str
    serial: str | None = None
    chain: str
    travel_mm: dict[Literal["X", "Y", "Z"], TravelRange]
    feed_mm_min: Feeds
    controller: Literal["sinumerik", "fanuc", "heidenhain", "linuxcnc", "isg"]
    receiver_offset_mm: Vector3
    spindle_angle_deg: Angle_deg = 0.0
    launch_unit: LaunchUnitGuess | None = None
    thermal: Thermal = Thermal()
    interferometer: InterferometerRanges = InterferometerRanges()
    uncertainty: Uncertainty = Uncertainty()
    measurement: Measurement = Measurement()
    cnc: Cnc = Cnc()
    smr_offset_mm: Vector3 = [0.0, 0.0, 0.0]
    #: further SMR positions by name (the ``smr`` column of tracker and tracer rows)
    smr_offsets_mm: dict[SmrName, Vector3] = {}
    tracker: TrackerUncertainty = TrackerUncertainty()
    tracer: TracerUncertainty = TracerUncertainty()
    _source: FileSource | None = PrivateAttr(default=None)

    @property
    def source(self) -> FileSource | None:
        """The machine file this machine was read from (role ``machine``), or None."""
        return self._source

    def __eq__(self, other: object) -> bool:
        """The same machine: the same keys and values, whichever file they came from."""
        return type(other) is type(self) and self.__dict__ == other.__dict__

    def __hash__(self) -> int:
        return super().__hash__()

    def model_copy(self, *, update: Mapping[str, Any] | None = None, deep: bool = False) -> Machine:
        """A copy; one with ``update`` is a machine no file describes (no :attr:`source`)."""
        copy = super().model_copy(update=update, deep=deep)
        if update:
            copy._source = None
        return copy

    @property
    def transit_feed_mm_min(self) -> float:
        """Feed between targets: the rapid feed, or the interferometer's tracking limit if lower."""
        limit = self.interferometer.max_speed_mm_min
        rapid = self.feed_mm_min.rapid
        return rapid if limit is None else min(rapid, limit)

    @model_validator(mode="after")
    def _series_of_the_family(self) -> Machine:
        known = SERIES[self.controller]
        if self.cnc.series is not None and self.cnc.series not in known:
            raise ValueError(
                f"cnc.series: '{self.cnc.series}' is not a {self.controller} series xmalign"
                f" knows (one of {', '.join(known)})"
            )
        return self

    @model_validator(mode="after")
    def _reference_in_the_travel(self) -> Machine:
        for axis, (low, high) in self.travel_mm.items():
            reference = float(self.cnc.reference["XYZ".index(axis)])
            if not low <= reference <= high:
                raise ValueError(
                    f"cnc.reference_mm: {axis} = {reference:g} mm is outside the travel"
                    f" [{low:g}, {high:g}] mm of travel_mm.{axis}"
                )
        return self

    @property
    def series(self) -> str:
        """The controller's series: ``cnc.series``, else the family's default."""
        return self.cnc.series or SERIES[self.controller][0]

    def reference_return(self, axis: str) -> Direction | None:
        """Direction of ``axis``'s reference return: ``cnc.reference_return``, else inferred.

        A reference point at (within 1 % of the stroke of) the travel's lower end is
        approached moving ``-``, at its upper end moving ``+``; one inside the travel
        leaves the direction unknown (None): a writer that needs it asks for the key.
        """
        given = next((d for a, d in self.cnc.reference_return.items() if a == axis), None)
        if given is not None:
            return given
        low, high = next(limits for a, limits in self.travel_mm.items() if a == axis)
        reference = float(self.cnc.reference["XYZ".index(axis)])
        margin = 0.01 * (high - low)
        if reference <= low + margin:
            return "-"
        if reference >= high - margin:
            return "+"
        return None

    def geometry_sha256(self) -> str:
        """Identity of the machine a plan is made for: SHA-256 of its geometry.

        Name, chain, travel, receiver offset and spindle angle (canonical JSON):
        what a plan's points and angles depend on. Sections that may change
        between ``program`` and ``post`` (uncertainties, feeds, ranges) do not count.
        """
        geometry = self.model_dump(
            mode="json",
            include={"name", "chain", "travel_mm", "receiver_offset_mm", "spindle_angle_deg"},
        )
        text = json.dumps(geometry, sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode("utf-8")).hexdigest()

    @field_validator("format")
    @classmethod
    def _known_format(cls, found: str | None) -> str | None:
        problem = None if found is None else format_problem(found, MACHINE_FORMAT)
        if problem is not None:
            raise ValueError(problem)
        return found

    @field_validator("chain")
    @classmethod
    def _chain_is_valid(cls, chain: str) -> str:
        letters = chain.upper()
        if sorted(letters) != sorted("FXYZ"):
            raise ValueError(f"'{chain}' must name F, X, Y and Z once each, e.g. FYXZ or XFYZ")
        return letters

    @field_validator("travel_mm")
    @classmethod
    def _travel_is_valid(cls, travel: dict[str, list[float]]) -> dict[str, list[float]]:
        missing = [axis for axis in AXES if axis not in travel]
        if missing:
            raise ValueError(f"axis {', '.join(missing)} missing")
        for axis, (low, high) in travel.items():
            if not (math.isfinite(low) and math.isfinite(high) and low < high):
                raise ValueError(f"{axis}: [{low}, {high}] must be finite with min < max")
            if high - low > MAX_LENGTH_MM:
                raise ValueError(f"{axis}: a travel of {high - low:g} mm is more than 100 m")
        return travel

    @property
    def travel_min_mm(self) -> Vec:
        """Lower travel limits ``[X, Y, Z]``, shape (3,)."""
        return np.array([self.travel_mm[a][0] for a in AXES], dtype=np.float64)

    @property
    def travel_max_mm(self) -> Vec:
        """Upper travel limits ``[X, Y, Z]``, shape (3,)."""
        return np.array([self.travel_mm[a][1] for a in AXES], dtype=np.float64)

    @property
    def spindle_angle_rad(self) -> float:
        return math.radians(self.spindle_angle_deg)

    @property
    def smr_offset(self) -> Vec:
        """SMR centre from the CNC tool point, spindle frame, mm, shape (3,)."""
        return np.asarray(self.smr_offset_mm, dtype=float)

    def smr_offsets(self) -> dict[str, Vec]:
        """The named SMR positions from the CNC tool point, spindle frame, mm, each (3,)."""
        return {name: np.asarray(v, dtype=float) for name, v in self.smr_offsets_mm.items()}

    @property
    def receiver_offset(self) -> Vec:
        """Receiver offset in the spindle frame, mm, shape (3,)."""
        return np.asarray(self.receiver_offset_mm, dtype=float)

    def within_travel(self, machine_mm: np.ndarray, tol_mm: float = 1e-6) -> np.ndarray:
        """True where CNC points (..., 3) lie inside the travel limits."""
        p = np.asarray(machine_mm, dtype=float)
        return np.all(
            (p >= self.travel_min_mm - tol_mm) & (p <= self.travel_max_mm + tol_mm), axis=-1
        )


def parse_machine(data: object, source: str = "<machine>") -> Machine:
    """Validate a machine mapping; raises InputError naming ``source`` and the key."""
    if not isinstance(data, dict):
        raise InputError(located(source, "top level", "expected a YAML mapping of machine keys"))
    return validate(Machine, data, source)


def load_machine(path: str | Path) -> Machine:
    """Read and validate a machine YAML file; the machine remembers it (:attr:`Machine.source`).

    Raises
    ------
    InputError
        ``path`` is not a path, or the file cannot be read or is not a valid machine file.
    """
    path = path_argument(path, "load_machine", "a machine file's path")
    source = FileSource.of("machine", path)
    machine = parse_machine(read_yaml(path), str(path))
    machine._source = source
    return machine


def default_machine_path() -> Path:
    """The reference machine shipped with xmalign (examples/fyxz.yaml)."""
    return Path(__file__).resolve().parent / "data" / "fyxz.yaml"
