"""Plots of a Monte Carlo study (matplotlib, Agg): histograms, beam envelopes, volumetric map."""

from __future__ import annotations

import io
import math
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after choosing the headless backend)
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from sim.mc import StrategyResult, quantity_label  # noqa: E402
from xmalign.formats.common import atomic_write_bytes  # noqa: E402

#: Which percentile of the trials the volumetric map shows at each point.
MAP_PERCENTILE = 95.0


def _grid(count: int, columns: int) -> tuple[Figure, np.ndarray]:
    rows = max(1, math.ceil(count / columns))
    figure, axes = plt.subplots(rows, columns, figsize=(4.2 * columns, 3.2 * rows), squeeze=False)
    for extra in axes.ravel()[count:]:
        extra.set_visible(False)
    return figure, axes.ravel()


def _save(figure: Figure, path: Path) -> Path:
    figure.tight_layout()
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=90)
    plt.close(figure)
    atomic_write_bytes(path, buffer.getvalue())
    return path


def histogram_range(values: np.ndarray) -> tuple[float, float]:
    """Range of a histogram that has room for 30 bins even for a (nearly) constant quantity.

    numpy refuses bins finer than the floating-point resolution of the values
    (``351 ± 1e-13``); the range is at least 1e-6 of the values' magnitude.
    """
    low, high = float(np.min(values)), float(np.max(values))
    span = max(high - low, 1e-6 * max(abs(low), abs(high)), 1e-9)
    centre = 0.5 * (low + high)
    return centre - 0.5 * span, centre + 0.5 * span


def plot_histograms(results: Sequence[StrategyResult], path: Path) -> Path:
    """One panel per quantity, the strategies' distributions overlaid."""
    names = list(dict.fromkeys(n for r in results for n in r.study.names))
    figure, axes = _grid(len(names), 4)
    for ax, name in zip(axes, names, strict=False):
        for result in results:
            values = result.study.values(name)
            if values.size:
                ax.hist(
                    values,
                    bins=30,
                    range=histogram_range(values),
                    histtype="step",
                    label=result.strategy.name,
                )
        ax.set_title(quantity_label(name), fontsize=8)
        ax.tick_params(labelsize=7)
    if names:
        axes[0].legend(fontsize=6)
    return _save(figure, path)


def plot_envelopes(results: Sequence[StrategyResult], path: Path) -> Path:
    """Per line, the predicted 95 % straightness radius along it: median and worst trial."""
    lines = list(dict.fromkeys(line for r in results for line in r.envelopes_um))
    figure, axes = _grid(len(lines), 3)
    along = None
    for ax, line in zip(axes, lines, strict=False):
        for k, result in enumerate(results):
            curves = np.array(result.envelopes_um.get(line, []))
            if not curves.size:
                continue
            along = np.linspace(0.0, 100.0, curves.shape[1])
            colour = f"C{k}"
            ax.plot(along, np.median(curves, axis=0), color=colour, label=result.strategy.name)
            ax.plot(along, curves.max(axis=0), color=colour, linestyle="--")
        limit = max((r.envelope_limit_um for r in results), default=math.nan)
        if math.isfinite(limit):
            ax.axhline(limit, color="red", linewidth=1)
        ax.set_title(f"line {line}: 95 % beam radius (median, -- worst)", fontsize=8)
        ax.set_xlabel("along the line, %", fontsize=7)
        ax.set_ylabel("um", fontsize=7)
        ax.tick_params(labelsize=7)
    if lines and along is not None:
        axes[0].legend(fontsize=6)
    return _save(figure, path)


def plot_volumetric_map(results: Sequence[StrategyResult], path: Path) -> Path | None:
    """Per strategy, the residual volumetric error after compensation on the grid (3D).

    The colour is the 95th percentile over the trials at each point; None when
    no trial computed a map (identification-only studies).
    """
    mapped = [r for r in results if r.volumetric_um and r.grid_mm is not None]
    if not mapped:
        return None
    levels = [np.percentile(np.array(r.volumetric_um), MAP_PERCENTILE, axis=0) for r in mapped]
    top = max(float(level.max()) for level in levels)
    columns = min(3, len(mapped))
    rows = math.ceil(len(mapped) / columns)
    figure = plt.figure(figsize=(4.5 * columns, 4.0 * rows))
    for k, (result, level) in enumerate(zip(mapped, levels, strict=True)):
        ax = figure.add_subplot(rows, columns, k + 1, projection="3d")
        grid = np.asarray(result.grid_mm)
        points = ax.scatter(
            grid[:, 0], grid[:, 1], grid[:, 2], c=level, cmap="viridis", vmin=0.0, vmax=top
        )
        ax.set_title(f"{result.strategy.name}\nP95 residual, um", fontsize=8)
        ax.set_xlabel("X mm", fontsize=7)
        ax.set_ylabel("Y mm", fontsize=7)
        ax.set_zlabel("Z mm", fontsize=7)
        ax.tick_params(labelsize=6)
        figure.colorbar(points, ax=ax, shrink=0.6)
    return _save(figure, path)
