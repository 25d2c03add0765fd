"""Monte Carlo planning of a calibration: the same random setups under several strategies.

A strategy is what the engineer decides before going on site: where the
launch unit stands, which identification positions (D-optimal design or
spread over the travel) and how many, the target spacing and the number of
runs. A trial draws a virtual setup from its seed (machine errors, unit
imperfections, placement of the launch unit around its planned position,
azimuth, instrument noise) and either

- ``identification``: simulates the identification session in closed form
  (:mod:`sim.identification`), identifies the pose and plans the lines
  (about 10 ms), or
- ``calibration``: runs the whole dry run (:func:`sim.dry_run.simulate_calibration`),
  about a second.

Every strategy sees the same seeds (common random numbers), so differences
between strategies are not differences between the machines they met.
"""

from __future__ import annotations

import itertools
import math
import tempfile
from collections.abc import Callable, Sequence
from concurrent.futures import Executor, as_completed
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from sim.dry_run import (
    DryRunOptions,
    measured_strokes,
    placement,
    simulate_calibration,
)
from sim.identification import SessionImperfections, simulate_session, spread_positions
from sim.machine import ErrorAmplitudes
from trajectories.identification_design import MIN_POSITIONS, count_problem
from trajectories.planner import MeasurementPlan
from xmalign.errors import InputError, XmalignError
from xmalign.formats.error_tables import read_error_tables
from xmalign.geometry import Vec, wrap_angle
from xmalign.identify import (
    METHODS,
    IdentificationResult,
)
from xmalign.machine import LaunchUnitGuess, Machine
from xmalign.montecarlo import AdaptiveStudy
from xmalign.post.compare import grid_points, remove_rigid_motion
from xmalign.rigid_body import Chain, ErrorModel, deviation
from xmalign.steps import design_step, plan_session_step

MODES = ("identification", "calibration")
#: Points along a line at which the predicted beam envelope is kept (fractions 0..1).
ENVELOPE_SAMPLES = 21
#: The random stream of an identification trial's session, apart from the placement's.
SESSION_STREAM = 1
#: Named launch-unit placements: the machine file's guess, its x and y moved to the centre
#: of the travel, or mirrored through the centre (the opposite corner), same height.
PLACEMENTS = ("guess", "centre", "opposite")
IDENTIFICATIONS = ("designed", "spread")


@dataclass(frozen=True)
class Strategy:
    """One way to carry out the calibration (None: as the machine file says)."""

    name: str = "baseline"
    placement: str = "guess"
    identification: str = "designed"
    alignments: int = 6
    target_spacing_mm: float | None = None
    runs: int | None = None
    diagonal_runs: int | None = None

    def machine(self, machine: Machine) -> Machine:
        """The machine file as this strategy uses it (launch position, measurement section)."""
        updates: dict[str, object] = {}
        if self.placement != "guess":
            updates["launch_unit"] = LaunchUnitGuess(
                position_mm=list(_placed(machine, self.placement))
            )
        measurement = {
            key: value
            for key, value in (
                ("target_spacing_mm", self.target_spacing_mm),
                ("runs", self.runs),
                ("diagonal_runs", self.diagonal_runs),
            )
            if value is not None
        }
        if measurement:
            updates["measurement"] = machine.measurement.model_copy(update=measurement)
        return machine.model_copy(update=updates)

    def identification_mm(self, machine: Machine) -> Vec:
        """CNC points (N, 3) mm at which this strategy aligns the units."""
        return self.identification_points(machine)[0]

    def identification_points(self, machine: Machine) -> tuple[Vec, list[str]]:
        """CNC points (N, 3) mm to align at and the design's warnings (none for spread)."""
        if self.identification == "spread":
            return spread_positions(machine, self.alignments), []
        design = design_step(machine, self.alignments)
        return design.machine_mm, list(design.warnings)


def _launch_guess_mm(machine: Machine) -> Vec:
    if machine.launch_unit is None:
        raise InputError(f"{machine.name}: the machine file has no launch_unit.position_mm")
    return np.asarray(machine.launch_unit.position_mm, dtype=float)


def _placed(machine: Machine, placement: str) -> Vec:
    guess = _launch_guess_mm(machine)
    centre = 0.5 * (machine.travel_min_mm + machine.travel_max_mm)
    if placement == "centre":
        return np.array([centre[0], centre[1], guess[2]])
    return np.array([2 * centre[0] - guess[0], 2 * centre[1] - guess[1], guess[2]])


def _positive_int(low: int) -> Callable[[str], int]:
    def parse(text: str) -> int:
        if not text.isdigit() or int(text) < low:
            raise ValueError(f"expected a whole number >= {low}")
        return int(text)

    return parse


def _alignments(text: str) -> int:
    count = _positive_int(MIN_POSITIONS)(text)
    problem = count_problem(count)
    if problem is not None:
        raise ValueError(problem)
    return count


def _spacing(text: str) -> float:
    value = float(text)
    if not 0 < value <= 200:
        raise ValueError("expected a spacing in (0, 200] mm")
    return value


def _one_of(choices: tuple[str, ...]) -> Callable[[str], object]:
    def parse(text: str) -> str:
        if text not in choices:
            raise ValueError(f"expected one of {', '.join(choices)}")
        return text

    return parse


@dataclass(frozen=True)
class Variation:
    """A decision ``--vary`` compares: the Strategy field it sets and its default values."""

    field: str
    parse: Callable[[str], object]
    defaults: Callable[[Machine], tuple[object, ...]]


VARIATIONS: dict[str, Variation] = {
    "launch-position": Variation("placement", _one_of(PLACEMENTS), lambda m: PLACEMENTS),
    "identification": Variation(
        "identification", _one_of(IDENTIFICATIONS), lambda m: IDENTIFICATIONS
    ),
    "alignments": Variation("alignments", _alignments, lambda m: (4, 6, 10)),
    "targets": Variation(
        "target_spacing_mm",
        _spacing,
        lambda m: (m.measurement.target_spacing_mm, m.measurement.target_spacing_mm / 2),
    ),
    "runs": Variation("runs", _positive_int(1), lambda m: (1, max(2, m.measurement.runs))),
    "diagonal-runs": Variation(
        "diagonal_runs", _positive_int(1), lambda m: (1, max(2, m.measurement.diagonal_runs))
    ),
}


def _variation_values(item: str, machine: Machine) -> tuple[str, Variation, tuple[object, ...]]:
    name, _, listed = item.partition("=")
    name = name.strip()
    if name not in VARIATIONS:
        raise InputError(f"--vary '{name}': unknown (choose {', '.join(VARIATIONS)})")
    variation = VARIATIONS[name]
    if not listed:
        return name, variation, tuple(dict.fromkeys(variation.defaults(machine)))
    values = []
    for text in listed.split(":"):
        try:
            values.append(variation.parse(text.strip()))
        except ValueError as error:
            raise InputError(f"--vary {name}: '{text}': {error}") from error
    return name, variation, tuple(dict.fromkeys(values))


def _label(name: str, value: object) -> str:
    if isinstance(value, float):
        return f"{name}={value:g}"
    return f"{name}={value}"


def strategies(machine: Machine, vary: Sequence[str]) -> list[Strategy]:
    """Every combination of the varied decisions; the others as the machine file says.

    Parameters
    ----------
    vary : sequence of str
        Items ``NAME`` (its default values) or ``NAME=V1:V2:...``, NAME one of
        :data:`VARIATIONS`.
    """
    chosen = [_variation_values(item, machine) for item in vary if item.strip()]
    if any(v.field == "placement" for _, v, _ in chosen) and machine.launch_unit is None:
        raise InputError(
            "--vary launch-position: the machine file has no launch_unit.position_mm to move"
        )
    if not chosen:
        return [Strategy()]
    result = []
    for combination in itertools.product(*(values for _, _, values in chosen)):
        updates: dict[str, Any] = {
            v.field: value for (_, v, _), value in zip(chosen, combination, strict=True)
        }
        name = ", ".join(
            _label(n, value) for (n, _, _), value in zip(chosen, combination, strict=True)
        )
        result.append(replace(Strategy(), name=name, **updates))
    return result


def trial_seed(seed: int, index: int) -> int:
    """The seed of trial ``index``, the same for every strategy."""
    return int(np.random.SeedSequence([seed, index]).generate_state(1)[0])


@dataclass(frozen=True)
class TrialSpec:
    """Everything one trial needs (picklable, to run in another process or on a Dask worker)."""

    mode: str
    machine: Machine
    identification_mm: Vec
    seed: int
    strategy_index: int = 0
    method: str = "joint"
    amplitudes: ErrorAmplitudes | None = None


@dataclass
class TrialOutcome:
    """What one trial found.

    Attributes
    ----------
    values : dict of str to float
        The reported quantities (see :func:`quantity_label`).
    envelope_um : dict of str to ndarray, shape (ENVELOPE_SAMPLES,)
        Per line, the predicted 95 % straightness radius along the line.
    envelope_limit_um : float
        The straightness the envelope must stay within (range minus allowance).
    volumetric_um : ndarray, shape (216,) or None
        Residual volumetric error after compensation at :attr:`grid_mm`.
    failure : str or None
        Why the trial could not finish (beam lost, singular identification...).
    """

    strategy_index: int
    values: dict[str, float] = field(default_factory=dict)
    envelope_um: dict[str, Vec] = field(default_factory=dict)
    envelope_limit_um: float = math.nan
    volumetric_um: Vec | None = None
    grid_mm: Vec | None = None
    failure: str | None = None


def _pose_values(result: IdentificationResult, position_mm: Vec, gamma_rad: float) -> dict:
    return {
        "position_error_um": float(np.linalg.norm(result.position_mm - position_mm) * 1e3),
        "gamma_error_urad": float(wrap_angle(result.gamma_rad - gamma_rad)) * 1e6,
    }


def _plan_outcome(plan: MeasurementPlan, strategy_index: int) -> TrialOutcome:
    """Predicted margins per line and the envelope along each line, from a plan."""
    outcome = TrialOutcome(strategy_index)
    along = np.linspace(0.0, 1.0, ENVELOPE_SAMPLES)
    for planned in plan.lines:
        line, envelope = planned.line.id, planned.envelope
        outcome.values[f"straightness_margin_um:{line}"] = envelope.straightness_margin_um
        outcome.values[f"angle_margin_urad:{line}"] = envelope.angle_margin_urad
        lateral = envelope.lateral_95_um
        outcome.envelope_um[line] = np.interp(along, np.linspace(0.0, 1.0, lateral.size), lateral)
        outcome.envelope_limit_um = envelope.straightness_limit_um
    return outcome


def identification_trial(spec: TrialSpec) -> TrialOutcome:
    """Identification only: closed-form session, then identify and plan the lines through
    the step layer (:func:`~xmalign.steps.plan_session_step`)."""
    machine = spec.machine
    truth = placement(machine, spec.seed)  # where the dry run of this seed places the unit
    position_mm, gamma_rad = truth.launch2mcs_mm, truth.gamma_rad
    rng = np.random.default_rng([spec.seed, SESSION_STREAM])
    imperfections = SessionImperfections.realistic(rng)
    session = simulate_session(
        spec.identification_mm,
        imperfections.truth(position_mm, gamma_rad),
        machine.receiver_offset,
        machine.spindle_angle_rad,
        imperfections,
        rng,
    )
    result, plan = plan_session_step(session, machine, spec.method)
    outcome = _plan_outcome(plan, spec.strategy_index)
    outcome.values = _pose_values(result, position_mm, gamma_rad) | outcome.values
    return outcome


def residual_map_um(
    chain: Chain, points_mm: Vec, truth: ErrorModel, compensated: ErrorModel
) -> Vec:
    """Length of the volumetric error left after compensation at each point, um, shape (N,).

    The rigid motion the six lines cannot see is removed as in
    :func:`xmalign.post.compare.volumetric_rms_um`.
    """
    dp_truth, _ = deviation(chain, points_mm, np.zeros(3), truth)
    dp_tables, _ = deviation(chain, points_mm, np.zeros(3), compensated)
    residual = remove_rigid_motion(points_mm, dp_truth - dp_tables)
    return np.linalg.norm(residual, axis=1) * 1e3


def calibration_trial(spec: TrialSpec) -> TrialOutcome:
    """The whole dry run in a temporary directory; adds margins seen, volumetric and time."""
    machine = spec.machine
    options = DryRunOptions(
        seed=spec.seed,
        method=spec.method,
        identification_mm=spec.identification_mm,
        amplitudes=spec.amplitudes,
    )
    with tempfile.TemporaryDirectory(prefix="xmalign-mc-") as workdir:
        report = simulate_calibration(machine, Path(workdir), options)
        tables = read_error_tables(report.files["errors"]).model()
    truth = report.truth  # the virtual machine the dry run measured
    grid = grid_points(*measured_strokes(report.plan))
    residual = residual_map_um(Chain.parse(machine.chain), grid, truth, tables)
    outcome = _plan_outcome(report.plan, spec.strategy_index)
    outcome.values = (
        _pose_values(report.identification, report.truth_launch2mcs_mm, report.truth_gamma_rad)
        | outcome.values
        | {f"measured_margin_um:{m.line}": m.measured_straightness_um for m in report.margins}
        | {
            "volumetric_before_um": report.volumetric_before_um,
            "volumetric_after_um": report.volumetric_after_um,
            "on_machine_min": report.on_machine_s / 60.0,
        }
    )
    outcome.volumetric_um, outcome.grid_mm = residual, grid
    return outcome


def run_trial(spec: TrialSpec) -> TrialOutcome:
    """One trial of ``spec.mode``; an xmalign error (beam lost...) is recorded as a failure."""
    trial = identification_trial if spec.mode == "identification" else calibration_trial
    try:
        return trial(spec)
    except XmalignError as error:
        return TrialOutcome(spec.strategy_index, failure=f"{type(error).__name__}: {error}")


_LABELS = {
    "position_error_um": "launch position error |dp|, um",
    "gamma_error_urad": "azimuth error, urad",
    "straightness_margin_um": "predicted straightness margin {line}, um",
    "angle_margin_urad": "predicted angle margin {line}, urad",
    "measured_margin_um": "measured straightness margin {line}, um",
    "volumetric_before_um": "volumetric error before comp (RMS), um",
    "volumetric_after_um": "volumetric error after comp (RMS), um",
    "on_machine_min": "on-machine time, min",
}


def quantity_label(name: str) -> str:
    """Human label of a quantity name such as ``straightness_margin_um:XY``."""
    base, _, line = name.partition(":")
    return _LABELS.get(base, base).format(line=line)


@dataclass
class StrategyResult:
    """Everything gathered for one strategy."""

    strategy: Strategy
    study: AdaptiveStudy
    trials: int = 0
    failures: list[str] = field(default_factory=list)
    envelopes_um: dict[str, list[Vec]] = field(default_factory=dict)
    volumetric_um: list[Vec] = field(default_factory=list)
    grid_mm: Vec | None = None
    envelope_limit_um: float = math.nan
    #: Why this strategy's identification design is not as good as planned.
    design_warnings: list[str] = field(default_factory=list)

    @property
    def stable(self) -> bool:
        return self.study.stable

    def add(self, outcomes: Sequence[TrialOutcome]) -> None:
        """Record one batch of trials."""
        self.trials += len(outcomes)
        done = [o for o in outcomes if o.failure is None]
        self.failures.extend(o.failure for o in outcomes if o.failure is not None)
        names = list(dict.fromkeys(name for o in done for name in o.values))
        self.study.add_batch({name: [o.values.get(name, math.nan) for o in done] for name in names})
        for outcome in done:
            for line, curve in outcome.envelope_um.items():
                self.envelopes_um.setdefault(line, []).append(curve)
            self.envelope_limit_um = outcome.envelope_limit_um
            if outcome.volumetric_um is not None:
                self.volumetric_um.append(outcome.volumetric_um)
                self.grid_mm = outcome.grid_mm


@dataclass(frozen=True)
class StudySettings:
    """How a Monte Carlo study runs (see ``xmalign mc --help``)."""

    mode: str = "identification"
    max_trials: int = 200
    batch: int = 50
    digits: int = 1
    seed: int = 0
    method: str = "joint"
    amplitudes: ErrorAmplitudes | None = None

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise InputError(f"--mode '{self.mode}': choose {' or '.join(MODES)}")
        if self.batch < 2 or self.max_trials < 2:
            raise InputError("--batch and --trials must be at least 2 (a batch needs a spread)")
        if self.digits < 1:
            raise InputError(f"--digits {self.digits}: must be at least 1")
        if self.method not in METHODS:
            raise InputError(f"--method '{self.method}': choose {', '.join(METHODS)}")


def run_study(
    machine: Machine,
    chosen: Sequence[Strategy],
    settings: StudySettings,
    executor: Executor,
    on_trial: Callable[[], None] | None = None,
) -> list[StrategyResult]:
    """Run batches of trials of every strategy until each is stable or has ``max_trials``.

    Trials run on ``executor`` (a process pool, or a Dask ``Client.get_executor()``);
    ``on_trial`` is called as each trial finishes.
    """
    if settings.mode == "identification" and machine.launch_unit is None:
        raise InputError("identification trials need launch_unit.position_mm in the machine file")
    machines = [strategy.machine(machine) for strategy in chosen]
    designs = [s.identification_points(m) for s, m in zip(chosen, machines, strict=True)]
    points = [design[0] for design in designs]
    results = [
        StrategyResult(s, AdaptiveStudy(settings.digits), design_warnings=design[1])
        for s, design in zip(chosen, designs, strict=True)
    ]
    while active := [
        k for k, r in enumerate(results) if r.trials < settings.max_trials and not r.stable
    ]:
        specs = [
            TrialSpec(
                settings.mode,
                machines[k],
                points[k],
                trial_seed(settings.seed, index),
                k,
                settings.method,
                settings.amplitudes,
            )
            for k in active
            for index in range(
                results[k].trials, min(results[k].trials + settings.batch, settings.max_trials)
            )
        ]
        outcomes: list[TrialOutcome] = []
        for future in as_completed([executor.submit(run_trial, spec) for spec in specs]):
            outcomes.append(future.result())
            if on_trial is not None:
                on_trial()
        for k in active:
            results[k].add([o for o in outcomes if o.strategy_index == k])
    return results
