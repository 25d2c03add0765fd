"""Gross outliers and dead channels: found, named, and never silently in the fit."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from sim.machine import VirtualMachine
from sim.synthetic import measure, six_line_plan
from xmalign.errors import InputError
from xmalign.formats.measurements import MeasurementRow
from xmalign.post.evaluate import PostResult, post_process
from xmalign.rigid_body import Chain
from xmalign.roles import CHANNELS


@pytest.fixture(scope="module")
def measurement(reference_machine):
    plan = six_line_plan(reference_machine, 12, runs=2, bidirectional=True)
    truth = VirtualMachine(reference_machine, seed=4)
    rows = measure(plan, Chain.parse(reference_machine.chain), truth, np.random.default_rng(9))
    return plan, rows


@pytest.fixture(scope="module")
def clean(reference_machine, measurement) -> PostResult:
    plan, rows = measurement
    return post_process(reference_machine, plan, rows, "m.csv")


def _changed(rows: list[MeasurementRow], key: tuple, channel: str, value: float | None = None):
    """The rows with one reading moved by ``value`` (None: set to zero) at ``key``."""
    k = CHANNELS.index(channel)
    out = []
    for row in rows:
        if row.key() == key:
            channels = row.channels.copy()
            channels[k] = 0.0 if value is None else channels[k] + value
            row = replace(row, channels=channels)
        out.append(row)
    return out


def test_clean_data_has_no_outlier(clean):
    assert clean.fit.outliers == []
    assert not any("outlier" in warning for warning in clean.warnings)


def test_a_linear_reading_500_um_off_is_named_and_left_out(reference_machine, measurement, clean):
    """The careless-user case of issue 22: sigma0 was 19.9 and EB0Z 73 urad off, silently."""
    plan, rows = measurement
    bad = _changed(rows, ("Y", 1, "+", 5), "linear_um", 500.0)
    result = post_process(reference_machine, plan, bad, "m.csv")
    assert len(result.fit.outliers) == 1
    (warning,) = [w for w in result.warnings if "outlier" in w]
    assert warning.startswith("m.csv: line Y run 1 direction + index 5: linear_um ")
    assert "left out of the fit" in warning
    assert result.fit.sigma0 == pytest.approx(clean.fit.sigma0, rel=0.1)
    for name, (value, u95) in clean.fit.tables.squareness.items():
        assert abs(result.fit.tables.squareness[name][0] - value) < u95 / 10, name


def _figures_of(result: PostResult, line: str) -> dict[str, float]:
    return next(f for f in result.positioning if f.line_id == line).as_dict()


def test_a_reading_left_out_of_the_fit_is_left_out_of_the_iso_figures_too(
    reference_machine, measurement, clean
):
    """Issue 32: the 500 um reading left the fit but stayed in ISO 230-2 (A 18 -> 1407 um)."""
    from xmalign.report import vdi_figures

    plan, rows = measurement
    bad = _changed(rows, ("Y", 1, "+", 5), "linear_um", 500.0)
    result = post_process(reference_machine, plan, bad, "m.csv")
    figures, before = _figures_of(result, "Y"), _figures_of(clean, "Y")
    assert figures["A"] == pytest.approx(before["A"], abs=2.0)  # one s_i fewer, not 1400 um
    assert figures["E"] == pytest.approx(before["E"], abs=2.0)
    assert all(np.isfinite(list(figures.values())))
    p_um = {v.line_id: v.P for v in vdi_figures(result)}
    p_clean_um = {v.line_id: v.P for v in vdi_figures(clean)}
    assert p_um["Y"] == pytest.approx(p_clean_um["Y"], abs=2.0)


def test_a_row_with_all_six_channels_at_zero_is_named_and_left_out(
    reference_machine, measurement, clean
):
    """Issue 32: its zeros stayed in the fit, as a perfect machine at that point."""
    plan, rows = measurement
    dead = [
        replace(row, channels=np.zeros(6)) if row.key() == ("Y", 1, "+", 5) else row for row in rows
    ]
    result = post_process(reference_machine, plan, dead, "m.csv")
    (warning,) = [w for w in result.warnings if "dead row" in w]
    assert warning.startswith("m.csv: line Y run 1 direction + index 5: all six channels")
    assert "left out of the fit" in warning
    (line_y,) = [data for data in result.lines if data.line.id == "Y"]
    assert len(line_y.run) == len([row for row in rows if row.line == "Y"]) - 1
    assert _figures_of(result, "Y")["A"] == pytest.approx(_figures_of(clean, "Y")["A"], abs=2.0)
    assert result.fit.sigma0 == pytest.approx(clean.fit.sigma0, rel=0.1)


@pytest.mark.parametrize("channels", [CHANNELS, ("angle_u_urad",)], ids=["all-six", "roll"])
def test_a_dead_channel_is_refused_naming_line_and_channel(
    reference_machine, measurement, channels
):
    """All six channels of line Z at zero (a dead instrument) gave sigma0 2.4 and EB0Z
    1011 urad off without a word; one dead channel must not enter the fit either."""
    plan, rows = measurement
    dead = [
        replace(row, channels=np.where(np.isin(CHANNELS, channels), 0.0, row.channels))
        if row.line == "Z"
        else row
        for row in rows
    ]
    with pytest.raises(InputError) as refused:
        post_process(reference_machine, plan, dead, "m.csv")
    message = str(refused.value)
    assert message.startswith("m.csv: line Z: " + ", ".join(channels) + " read exactly 0 at all")
    assert "dead or unplugged" in message


def test_more_gross_outliers_than_the_limit_refuse_the_measurement(reference_machine, measurement):
    from xmalign.post.solve import MAX_OUTLIERS

    plan, rows = measurement
    bad = rows
    for index in range(MAX_OUTLIERS + 1):
        bad = _changed(bad, ("X", 1, "+", index), "straightness_v_um", 300.0 * (-1) ** index)
    with pytest.raises(InputError, match=f"more than {MAX_OUTLIERS} readings are gross outliers"):
        post_process(reference_machine, plan, bad, "m.csv")


def test_a_run_outside_the_plan_is_refused(reference_machine, measurement):
    plan, rows = measurement
    moved = [replace(row, run=7) if row.key() == ("Z", 2, "+", 3) else row for row in rows]
    with pytest.raises(InputError, match="m.csv: line Z run 7 index 3: the plan has runs 1..2"):
        post_process(reference_machine, plan, moved, "m.csv")


def test_an_index_beyond_the_targets_is_refused_before_the_air_compensation(
    reference_machine, measurement
):
    """It was an IndexError in compensate_line."""
    plan, rows = measurement
    moved = [replace(row, index=99) if row.key() == ("Z", 2, "+", 3) else row for row in rows]
    with pytest.raises(InputError, match="m.csv: line Z run 2: target index 99 is not in the"):
        post_process(reference_machine, plan, moved, "m.csv")
