"""What ``xmalign mc`` shows and draws: a table that fits 100 columns, robust histograms."""

import numpy as np
import pytest
from rich.console import Console

from sim.mc import Strategy, StrategyResult
from sim.mc_plots import histogram_range, plot_histograms
from tests.xmalign.bad_input_cases import run_main
from xmalign.cli.mc import _plot, _table, estimate_decimals
from xmalign.montecarlo import AdaptiveStudy


def _results(rng):
    results = []
    for k, name in enumerate(["alignments=10, runs=2", "identification=spread, targets=50"]):
        study = AdaptiveStudy()
        study.add_batch(
            {
                "position_error_um": rng.normal(25 + k, 1.2, 40),
                "straightness_margin_um:XY": rng.normal(1234.5, 12.0, 40),
                "angle_margin_urad:Z": 351.0 + rng.normal(0, 1.7e-8, 40),
                "gamma_error_urad": np.full(40, 7.0),  # constant
            }
        )
        results.append(StrategyResult(Strategy(name=name), study, trials=40))
    return results


@pytest.mark.parametrize(
    ("mean", "u", "decimals"),
    [(152.8, 6.1, 1), (351.0, 1.7e-8, 1), (25.3, 1.2, 1), (0.0123, 0.0004, 5), (7.0, 0.0, 3)],
)
def test_estimates_have_sensible_digits(mean, u, decimals):
    assert estimate_decimals(mean, u) == decimals


def test_the_table_fits_100_columns_one_line_per_row():
    console = Console(width=100, record=True, color_system=None)
    console.print(_table(_results(np.random.default_rng(1)), 30.0, "identification"))
    lines = console.export_text().splitlines()
    assert max(len(line) for line in lines) <= 100 and "…" not in "".join(lines)
    assert any("351.0 ± 0.0" in line and "[351.0, 351.0]" in line for line in lines)
    assert any("identification=spread, targets=50" in line for line in lines)
    rows = [line for line in lines if "alignments=10" in line or "targets=50" in line]
    assert len(rows) == 2 * 7  # 4 quantities, tolerance, trials, stable; nothing wrapped


@pytest.mark.parametrize("offset", [0.0, 351.0, 1e6])
def test_a_histogram_of_a_constant_quantity_is_drawn(tmp_path, offset):
    for values in (np.full(20, offset), offset + np.linspace(0, 1e-13 * max(offset, 1), 20)):
        low, high = histogram_range(values)
        assert low <= values.min() and values.max() <= high
        np.histogram(values, bins=30, range=(low, high))  # numpy's own check passes
    assert plot_histograms(_results(np.random.default_rng(2)), tmp_path / "h.png").exists()


def test_a_plot_failure_is_a_warning(capsys):
    def broken():
        raise ValueError("Too many bins for data range")

    assert _plot(broken, "histograms.png") is None
    assert "warning: histograms.png not drawn (ValueError: Too many bins" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("option", "value", "named"),
    [
        ("--error-scale", "-0.5", "--error-scale"),
        ("--squareness-urad", "-1", "--squareness-urad"),
        ("--workers", "-2", "--workers"),
    ],
)
def test_mc_refuses_a_negative_setting_before_any_trial(tmp_path, option, value, named):
    out = tmp_path / "mc"
    code, stderr, escaped = run_main(("mc", "--trials", "2", option, value, "--out", str(out)))
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert (code, escaped) == (2, "")
    assert len(lines) == 1 and lines[0].startswith("xmalign: error: ") and named in lines[0]
    assert not out.exists()  # refused before a trial ran or a file was written


@pytest.mark.parametrize(
    ("mean", "u"), [(float("inf"), 1.0), (float("nan"), float("nan")), (0.0, 0.0)]
)
def test_an_estimate_without_a_resolution_shows_no_decimals(mean, u):
    # all trials failed (nan), diverged (inf) or exactly zero: the table still draws
    assert estimate_decimals(mean, u) == 0
