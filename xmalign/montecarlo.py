"""Monte Carlo statistics and the adaptive procedure of GUM Supplement 1 (JCGM 101:2008, 7.9).

A Monte Carlo study reports, for every output quantity, its mean, its standard
uncertainty and the probabilistically symmetric coverage interval (7.7).
Trials are added in batches; after each batch the study is stable when, for
every quantity, twice the standard deviation of the batch values of each of
those four numbers is at most the numerical tolerance ``delta`` of the
standard uncertainty for the number of significant digits asked for (7.9.2,
7.9.4).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from xmalign.geometry import Vec

#: Coverage probability of the reported intervals.
COVERAGE = 0.95
#: The four numbers of a summary whose batch values must settle, in order.
STABILISED = ("mean", "standard_uncertainty", "low", "high")


@dataclass(frozen=True)
class Summary:
    """Mean, standard uncertainty and coverage interval of one quantity's Monte Carlo values."""

    mean: float
    standard_uncertainty: float
    low: float
    high: float
    count: int

    def as_array(self) -> Vec:
        """``(mean, standard_uncertainty, low, high)``, shape (4,)."""
        return np.array([getattr(self, name) for name in STABILISED])


def summarize(values: ArrayLike, coverage: float = COVERAGE) -> Summary:
    """Summary of Monte Carlo values (GUM S1 7.6, 7.7).

    Parameters
    ----------
    values : array_like, shape (M,)
        At least two finite values.
    coverage : float
        Coverage probability of the probabilistically symmetric interval, whose
        ends are the ``(1 -+ p) / 2`` quantiles (linear interpolation between
        order statistics).
    """
    y = np.asarray(values, dtype=float).ravel()
    if y.size < 2:
        raise ValueError(f"a Monte Carlo summary needs at least 2 values, got {y.size}")
    low, high = np.quantile(y, [(1 - coverage) / 2, (1 + coverage) / 2])
    return Summary(float(y.mean()), float(y.std(ddof=1)), float(low), float(high), int(y.size))


def numerical_tolerance(standard_uncertainty: float, digits: int) -> float:
    """GUM S1 7.9.2: write ``u = c x 10**l`` with ``c`` a ``digits``-digit integer; ``0.5 x 10**l``.

    Zero for ``u == 0`` (a constant quantity is stable only when nothing varies).
    """
    if digits < 1:
        raise ValueError(f"significant digits must be at least 1, got {digits}")
    u = abs(standard_uncertainty)
    if u == 0.0:
        return 0.0
    exponent = math.floor(math.log10(u)) - digits + 1
    if round(u / 10.0**exponent) >= 10**digits:  # u rounds up to one more digit, e.g. 0.0996
        exponent += 1
    return 0.5 * 10.0**exponent


@dataclass(frozen=True)
class Stability:
    """How settled one quantity is after ``batches`` batches.

    Attributes
    ----------
    tolerance : float
        Numerical tolerance ``delta`` of the standard uncertainty of all values.
    spread : ndarray, shape (4,)
        Twice the standard deviation of the average of the batch values of
        mean, standard uncertainty, low and high end (inf with fewer than 2 batches).
    """

    tolerance: float
    spread: Vec
    batches: int

    @property
    def stable(self) -> bool:
        return self.batches >= 2 and bool(np.all(self.spread <= self.tolerance))


def stability(batches: Sequence[ArrayLike], digits: int, coverage: float = COVERAGE) -> Stability:
    """GUM S1 7.9.4 f) to i) for one quantity: are its results stable to ``digits`` digits?

    Parameters
    ----------
    batches : sequence of array_like
        The values of each batch of trials (batches with fewer than 2 values are
        ignored; their values still count towards the standard uncertainty).
    digits : int
        Significant decimal digits regarded as meaningful in the standard uncertainty.
    """
    arrays = [np.asarray(b, dtype=float).ravel() for b in batches]
    every = np.concatenate(arrays) if arrays else np.empty(0)
    tolerance = (
        numerical_tolerance(summarize(every, coverage).standard_uncertainty, digits)
        if every.size >= 2
        else math.inf
    )
    per_batch = np.array([summarize(b, coverage).as_array() for b in arrays if b.size >= 2])
    h = len(per_batch)
    if h < 2:
        return Stability(tolerance, np.full(4, math.inf), h)
    spread = 2.0 * per_batch.std(axis=0, ddof=1) / math.sqrt(h)
    return Stability(tolerance, spread, h)


@dataclass
class AdaptiveStudy:
    """Values of several named quantities gathered batch by batch, with the stopping rule.

    Non-finite values (a failed trial has none) are left out of the statistics.
    """

    digits: int = 1
    coverage: float = COVERAGE
    batches: list[dict[str, Vec]] = field(default_factory=list)

    def add_batch(self, values: Mapping[str, ArrayLike]) -> None:
        """Record one batch: for each quantity its values, shape (M,)."""
        batch = {}
        for name, array in values.items():
            y = np.asarray(array, dtype=float).ravel()
            batch[name] = y[np.isfinite(y)]
        self.batches.append(batch)

    @property
    def names(self) -> list[str]:
        """Every quantity seen, in the order first recorded."""
        return list(dict.fromkeys(name for batch in self.batches for name in batch))

    def values(self, name: str) -> Vec:
        """All finite values of one quantity, shape (M,)."""
        parts = [batch[name] for batch in self.batches if name in batch]
        return np.concatenate(parts) if parts else np.empty(0)

    def stability(self) -> dict[str, Stability]:
        return {
            name: stability(
                [batch[name] for batch in self.batches if name in batch],
                self.digits,
                self.coverage,
            )
            for name in self.names
        }

    @property
    def stable(self) -> bool:
        """True when every quantity is stable (GUM S1 7.9.4 i)."""
        settled = self.stability()
        return bool(settled) and all(s.stable for s in settled.values())

    def summaries(self) -> dict[str, Summary]:
        """Summary of every quantity with at least two values."""
        return {
            name: summarize(self.values(name), self.coverage)
            for name in self.names
            if self.values(name).size >= 2
        }
