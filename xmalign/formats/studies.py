"""The planning files: identification design (``xmalign.identify-design/1``) and the
Monte Carlo study (``xmalign-mc/1``) of docs/formats.md, written and read here.

Both carry the history keys of :mod:`xmalign.formats.provenance`; files written
before them (without) are read as well.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import Field

from xmalign.formats.common import FileModel, Finite, Vector3_mm, read_json, validate, write_json
from xmalign.formats.provenance import FileSource, Provenance, json_history, read_json_history
from xmalign.geometry import Vec

DESIGN_FORMAT = "xmalign.identify-design/1"
MC_FORMAT = "xmalign-mc/1"


class _DesignModel(FileModel):
    machine: str
    machine_mm: Annotated[list[Vector3_mm], Field(min_length=1)]
    predicted_covariance: Annotated[
        list[Annotated[list[Finite], Field(min_length=4, max_length=4)]],
        Field(min_length=4, max_length=4),
    ]


@dataclass
class DesignFile:
    """Proposed identification positions: CNC points (N, 3) mm and the predicted
    covariance of (x mm, y mm, z mm, gamma rad), (4, 4)."""

    machine: str
    machine_mm: Vec
    predicted_covariance: Vec
    history: Provenance | None = None


def write_design(
    path: str | Path,
    machine: str,
    machine_mm: Vec,
    predicted_covariance: Vec,
    inputs: Iterable[FileSource] = (),
) -> None:
    """Write the identification design with its history (``inputs``: the machine file)."""
    write_json(
        path,
        json_history(DESIGN_FORMAT, inputs)
        | {
            "machine": machine,
            "machine_mm": np.asarray(machine_mm, dtype=float).tolist(),
            "predicted_covariance": np.asarray(predicted_covariance, dtype=float).tolist(),
        },
    )


def read_design(path: str | Path) -> DesignFile:
    """Read an identification design written by ``xmalign plan-identify --out``."""
    data = read_json(path, DESIGN_FORMAT)
    model = validate(_DesignModel, data, str(path))
    return DesignFile(
        model.machine,
        np.array(model.machine_mm, dtype=float),
        np.array(model.predicted_covariance, dtype=float),
        read_json_history(data, str(path)),
    )


class _SummaryModel(FileModel):
    mean: Finite | None
    standard_uncertainty: Finite | None
    low_95: Finite | None
    high_95: Finite | None
    count: Annotated[int, Field(ge=0)]


class _StrategyModel(FileModel):
    name: str
    trials: Annotated[int, Field(ge=0)]
    failed: Annotated[int, Field(ge=0)] = 0
    stable: bool = False
    quantities: dict[str, _SummaryModel]


class _StudyModel(FileModel):
    machine: str
    mode: str
    seed: Annotated[int, Field(ge=0)]
    strategies: list[_StrategyModel]


@dataclass(frozen=True)
class QuantitySummary:
    """One quantity over a strategy's trials: mean, standard uncertainty, 95 % interval."""

    mean: float
    standard_uncertainty: float
    low_95: float
    high_95: float
    count: int


@dataclass
class StrategySummary:
    """One strategy of a study: its name, trials, failures and quantities by name."""

    name: str
    trials: int
    failed: int
    stable: bool
    quantities: dict[str, QuantitySummary]
    settings: dict[str, Any] = field(default_factory=dict)


@dataclass
class StudyFile:
    """A Monte Carlo study as written by ``xmalign mc``."""

    machine: str
    mode: str
    seed: int
    strategies: list[StrategySummary]
    history: Provenance | None = None


def study_document(body: dict[str, Any], inputs: Iterable[FileSource] = ()) -> dict[str, Any]:
    """The mc.json document: history keys, then ``body`` (machine, mode, strategies...)."""
    return json_history(MC_FORMAT, inputs) | body


def read_study(path: str | Path) -> StudyFile:
    """Read an ``mc.json`` written by ``xmalign mc`` (a quantity without trials is NaN)."""
    data = read_json(path, MC_FORMAT)
    model = validate(_StudyModel, data, str(path))

    def number(value: float | None) -> float:
        return float("nan") if value is None else value

    strategies = [
        StrategySummary(
            s.name,
            s.trials,
            s.failed,
            s.stable,
            {
                name: QuantitySummary(
                    number(q.mean),
                    number(q.standard_uncertainty),
                    number(q.low_95),
                    number(q.high_95),
                    q.count,
                )
                for name, q in s.quantities.items()
            },
            settings=dict(_settings(data, index)),
        )
        for index, s in enumerate(model.strategies)
    ]
    return StudyFile(
        model.machine, model.mode, model.seed, strategies, read_json_history(data, str(path))
    )


def _settings(data: dict[str, Any], index: int) -> Sequence[tuple[str, Any]]:
    """The strategy's decisions as written (placement, identification, alignments, ...)."""
    known = {"name", "trials", "failed", "stable", "quantities", "failures"}
    return [(k, v) for k, v in data["strategies"][index].items() if k not in known]
