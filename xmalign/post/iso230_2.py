"""ISO 230-2 positioning figures of an axis line from its linear channel.

With ``x_ij`` the positional deviation at target ``i`` in run ``j`` (um), per
direction (up = the line's ``+`` pass): mean ``x̄_i``, standard uncertainty
estimator ``s_i`` (n - 1), reversal ``B_i = x̄_i↑ - x̄_i↓`` and

- repeatability ``R↑ = max 4 s_i↑``, bidirectional
  ``R = max(2 s_i↑ + 2 s_i↓ + |B_i|, R_i↑, R_i↓)``;
- systematic deviation ``E↑ = max x̄_i↑ - min x̄_i↑``, ``E`` over both directions;
- mean bidirectional deviation ``M = max x̄_i - min x̄_i``, ``x̄_i = (x̄_i↑ + x̄_i↓) / 2``;
- reversal ``B = max |B_i|`` and mean reversal ``B̄``;
- accuracy ``A↑ = max(x̄_i↑ + 2 s_i↑) - min(x̄_i↑ - 2 s_i↑)``, ``A`` over both directions.

Figures that need a quantity the data lacks (one run: no ``s``; one direction:
no reversal) are NaN. A target left with one reading in a direction (a reading
left out of the fit as a gross outlier or a dead row is left out here too) has
no ``s_i`` there: the figures that need it are taken over the other targets.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from xmalign.geometry import Vec

NAN = math.nan


@dataclass(frozen=True)
class PositioningFigures:
    """ISO 230-2 figures of one line, um (NaN where the data cannot give one)."""

    line_id: str
    runs: int
    A_up: float = NAN
    A_down: float = NAN
    A: float = NAN
    B: float = NAN
    B_mean: float = NAN
    E_up: float = NAN
    E_down: float = NAN
    E: float = NAN
    M: float = NAN
    R_up: float = NAN
    R_down: float = NAN
    R: float = NAN

    def as_dict(self) -> dict[str, float]:
        """The figures by name (without the line id and run count)."""
        return {
            f.name: getattr(self, f.name) for f in fields(self) if f.name not in ("line_id", "runs")
        }


@dataclass
class _Direction:
    mean: Vec
    std: Vec


def _statistics(index: np.ndarray, deviation_um: Vec, n: int) -> _Direction:
    mean, std = np.full(n, np.nan), np.full(n, np.nan)
    for i in range(n):
        values = deviation_um[index == i]
        if len(values):
            mean[i] = values.mean()
            std[i] = values.std(ddof=1) if len(values) > 1 else np.nan
    return _Direction(mean, std)


def _max(values: Vec) -> float:
    """The largest value that is not NaN (NaN if none is: the data cannot give it)."""
    finite = values[~np.isnan(values)]
    return float(np.max(finite)) if finite.size else NAN


def _min(values: Vec) -> float:
    return -_max(-values)


def _span(values: Vec) -> float:
    return _max(values) - _min(values)


def positioning_figures(
    line_id: str, index: np.ndarray, sign: Vec, run: np.ndarray, deviation_um: Vec
) -> PositioningFigures:
    """ISO 230-2 figures from the deviations of one line.

    Parameters
    ----------
    index, sign, run : ndarray, shape (N,)
        Target index, pass direction (+1 / -1) and run of every point.
    deviation_um : ndarray, shape (N,)
        Positional deviation (actual minus target), um.
    """
    n = int(index.max()) + 1
    runs = len(np.unique(run))
    passes = {
        s: _statistics(index[sign == s], deviation_um[sign == s], n)
        for s in (1.0, -1.0)
        if np.any(sign == s)
    }
    values: dict[str, float] = {}
    for s, suffix in ((1.0, "up"), (-1.0, "down")):
        if s in passes:
            d = passes[s]
            values[f"E_{suffix}"] = _span(d.mean)
            values[f"R_{suffix}"] = _max(4 * d.std)
            values[f"A_{suffix}"] = _max(d.mean + 2 * d.std) - _min(d.mean - 2 * d.std)
    if len(passes) == 2:
        up, down = passes[1.0], passes[-1.0]
        reversal = up.mean - down.mean
        values["B"] = _max(np.abs(reversal))
        values["B_mean"] = float(np.nanmean(reversal))
        values["E"] = _span(np.concatenate([up.mean, down.mean]))
        values["M"] = _span(0.5 * (up.mean + down.mean))
        bidirectional = 2 * up.std + 2 * down.std + np.abs(reversal)
        values["R"] = _max(np.maximum(bidirectional, 4 * np.maximum(up.std, down.std)))
        values["A"] = _max(np.maximum(up.mean + 2 * up.std, down.mean + 2 * down.std)) - _min(
            np.minimum(up.mean - 2 * up.std, down.mean - 2 * down.std)
        )
    return PositioningFigures(line_id=line_id, runs=runs, **values)


#: ISO 230-2 asks for five runs in each direction (axes up to 2000 mm).
ISO_230_2_RUNS = 5


def runs_note(figures: PositioningFigures) -> str | None:
    """The report's note when a line has fewer runs than ISO 230-2 asks for, else None."""
    if figures.runs >= ISO_230_2_RUNS:
        return None
    return (
        f"line {figures.line_id}: {figures.runs} run(s), ISO 230-2 asks for"
        f" {ISO_230_2_RUNS}; the repeatability and accuracy figures rest on fewer samples"
        " than the standard assumes"
    )


@dataclass(frozen=True)
class VdiFigures:
    """VDI/DGQ 3441 figures of one line, um (NaN where the data cannot give one).

    ``P`` position uncertainty, ``Ps`` maximum position scatter, ``U`` maximum
    reversal span, ``Pa`` positional deviation.
    """

    line_id: str
    P: float = NAN
    Ps: float = NAN
    U: float = NAN
    Pa: float = NAN

    def as_dict(self) -> dict[str, float]:
        return {"P": self.P, "Ps": self.Ps, "U": self.U, "Pa": self.Pa}


def vdi3441_figures(line_id: str, index: np.ndarray, sign: Vec, deviation_um: Vec) -> VdiFigures:
    """VDI/DGQ 3441 figures from the deviations of one bidirectional line.

    Per target ``j``: mean ``x̄_j = (x̄_j↑ + x̄_j↓)/2``, scatter
    ``Ps_j = 6·(s_j↑ + s_j↓)/2``, reversal ``U_j = |x̄_j↑ − x̄_j↓|``; then
    ``Ps = max Ps_j``, ``U = max U_j``, ``Pa = max x̄_j − min x̄_j`` and
    ``P = max(x̄_j + (U_j + Ps_j)/2) − min(x̄_j − (U_j + Ps_j)/2)``.
    Arguments as :func:`positioning_figures`; one direction only gives NaN.
    """
    n = int(index.max()) + 1
    if not (np.any(sign > 0) and np.any(sign < 0)):
        return VdiFigures(line_id)
    up = _statistics(index[sign > 0], deviation_um[sign > 0], n)
    down = _statistics(index[sign < 0], deviation_um[sign < 0], n)
    mean = 0.5 * (up.mean + down.mean)
    scatter = 6.0 * 0.5 * (up.std + down.std)
    reversal = np.abs(up.mean - down.mean)
    half = 0.5 * (reversal + scatter)
    return VdiFigures(
        line_id,
        P=_max(mean + half) - _min(mean - half),
        Ps=_max(scatter),
        U=_max(reversal),
        Pa=_span(mean),
    )
