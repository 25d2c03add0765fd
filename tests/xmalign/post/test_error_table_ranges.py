"""Tables over the whole travel: extrapolated points, their u95 and the ``range`` column."""

from __future__ import annotations

import numpy as np
import pytest

from sim.machine import VirtualMachine
from sim.synthetic import measure, six_line_plan
from xmalign.errors import InputError
from xmalign.formats.error_tables import read_error_tables, write_error_tables
from xmalign.post.evaluate import post_process
from xmalign.post.solve import spline_basis
from xmalign.rigid_body import Chain


def test_the_spline_follows_a_cubic_and_continues_linearly():
    knots = np.array([0.0, 1.0, 3.0, 4.0, 6.0])
    cubic = np.polynomial.Polynomial([1.0, -2.0, 0.5, 0.25])
    slope = cubic.deriv()
    inside = np.array([0.5, 2.0, 3.0, 5.2])
    basis = spline_basis(knots, np.concatenate([inside, [-1.0, 8.0]])).toarray()
    expected = np.concatenate(
        [cubic(inside), [cubic(0.0) - slope(0.0), cubic(6.0) + 2.0 * slope(6.0)]]
    )
    assert np.allclose(basis @ cubic(knots), expected)
    assert np.count_nonzero(basis[:4], axis=1).max() <= 5  # local


def test_two_knots_give_a_straight_line():
    basis = spline_basis(np.array([0.0, 2.0]), np.array([-1.0, 1.0, 3.0])).toarray()
    assert np.allclose(basis @ np.array([1.0, 3.0]), [0.0, 2.0, 4.0])


@pytest.fixture(scope="module")
def short_lines(reference_machine):
    """Six lines that stop 200 mm short of the X, Y and Z travel's upper end."""
    machine = reference_machine
    plan = six_line_plan(machine, 12, runs=1, bidirectional=False)
    for line in plan.lines:
        line.targets_mm = line.targets_mm[line.targets_mm <= line.targets_mm[-1] - 200.0]
    rows = measure(
        plan, Chain.parse(machine.chain), VirtualMachine(machine, seed=8), np.random.default_rng(1)
    )
    return post_process(machine, plan, rows, "m.csv")


def test_tables_reach_the_travel_ends_with_growing_u95(short_lines, reference_machine):
    table = short_lines.fit.tables.tables["EXX"]
    measured = table.measured_mask()
    assert table.positions_mm[-1] == reference_machine.travel_max_mm[0]
    assert not measured[-1] and measured[:-1].all()
    assert table.u95[-1] > table.u95[-2]


def test_the_range_column_round_trips(short_lines, tmp_path):
    path = tmp_path / "errors.csv"
    write_error_tables(path, short_lines.fit.tables)
    header = [line for line in path.read_text().splitlines() if not line.startswith("#")][0]
    assert header.endswith(",u95,range")
    again = read_error_tables(path).tables["EXX"]
    assert np.array_equal(again.measured_mask(), short_lines.fit.tables.tables["EXX"].measured)


def test_a_file_without_the_range_column_is_all_measured(tmp_path):
    path = tmp_path / "old.csv"
    squareness = "EC0Y,,0,urad,1\nEA0Z,,0,urad,1\nEB0Z,,0,urad,1\n"
    path.write_text(
        "name,position_mm,value,unit,u95\nEXX,0,0,um,0\nEXX,100,2.5,um,0.4\n" + squareness
    )
    assert read_error_tables(path).tables["EXX"].measured_mask().all()


def test_an_unknown_range_is_refused(tmp_path):
    path = tmp_path / "bad.csv"
    path.write_text("name,position_mm,value,unit,u95,range\nEXX,0,0,um,0,guessed\n")
    expected = "bad.csv: line 2: range: .guessed. must be .measured. or .extrapolated."
    with pytest.raises(InputError, match=expected):
        read_error_tables(path)


def test_the_report_names_the_measured_and_extrapolated_ranges(short_lines):
    from xmalign.post.ranges import range_rows
    from xmalign.report import error_curves_figure

    rows = {row[0]: row[1:] for row in range_rows(short_lines.fit.tables)}
    assert rows["X"] == ["0 to 1636.36", "1636.36 to 2000"]
    figure = error_curves_figure(short_lines.fit.tables, "X")
    assert all(len(panel.patches) == 1 for panel in figure.axes)  # the grey extrapolated span
