"""The shared fit of each controller's model to the error field over the whole travel."""

from __future__ import annotations

import numpy as np
import pytest

from tests.xmalign.comp.conftest import make_machine, make_tables, with_reversal
from xmalign.comp import compensate, fit_for, remaining_errors
from xmalign.comp.fit import CROSS, PITCH, CompModel, fit_compensation, travel_grid
from xmalign.rigid_body import AXES, Chain, deviation


def _fit(model, tables, machine, tool=(0.0, 0.0, 0.0)):
    return fit_compensation(
        model,
        tables,
        Chain.parse(machine.chain),
        (machine.travel_min_mm, machine.travel_max_mm),
        np.array(tool),
        machine.cnc.reference,
    )


def test_pitch_takes_out_a_pure_positioning_error_and_is_zero_at_the_reference(machine):
    tables = make_tables({"EXX": [4, 10, 12, 5, 0]})
    fit = _fit(CompModel(PITCH, directional=False), tables, machine)
    positions, values = fit.table("X", "X")
    np.testing.assert_allclose(values * 1e3, [0, 6, 8, 1, -4], atol=1e-9)  # zero at x = 0
    assert fit.after_um == pytest.approx(0.0, abs=1e-9) and fit.before_um > 3.0


def test_reference_point_from_the_machine_file():
    tables = make_tables({"EXX": [4, 10, 12, 5, 0]})
    fit = _fit(CompModel(PITCH, False), tables, make_machine(reference_mm=[200.0, 0.0, 0.0]))
    assert np.interp(200.0, *fit.table("X", "X")) == pytest.approx(0.0, abs=1e-12)


def test_squareness_needs_a_cross_table(machine):
    tables = make_tables(EC0Y=20.0)  # a move y deviates by -y * EC0Y in X
    pitch = _fit(CompModel(PITCH, False), tables, machine)
    cross = _fit(CompModel(CROSS, False), tables, machine)
    assert pitch.after_um == pytest.approx(pitch.before_um)
    assert cross.after_um == pytest.approx(0.0, abs=1e-9)
    _, exy = cross.table("X", "Y")
    np.testing.assert_allclose(exy * 1e3, -20e-6 * np.linspace(0, 300, 5) * 1e3, atol=1e-9)


def test_abbe_error_of_a_constant_pitch_is_a_cross_table_of_the_lever_axis(machine):
    # FYXZ: the X lever arm is z, so EBX = b gives dp_x = b * z, a function of z alone
    tables = make_tables({"EBX": [30] * 5})
    fit = _fit(CompModel(CROSS, False), tables, machine)
    assert fit.after_um == pytest.approx(0.0, abs=1e-9)
    _, exz = fit.table("X", "Z")
    np.testing.assert_allclose(exz, 30e-6 * (np.linspace(-200, 0, 5) - 0.0), atol=1e-12)


def test_the_fit_is_least_squares_over_the_grid(machine):
    """No small change of any fitted table lowers the residual (a bilinear Abbe term stays)."""
    rng = np.random.default_rng(5)
    tables = make_tables(
        {name: rng.normal(0, 5, 5) for name in ("EXX", "EYX", "EBX", "ECY", "EZZ")}
    )
    model = CompModel(CROSS, False)
    fit = _fit(model, tables, machine)
    assert 0.0 < fit.after_um < fit.before_um
    chain = Chain.parse(machine.chain)
    nodes = {axis: tables.positioning_table(axis).positions_mm for axis in AXES}
    points = travel_grid(nodes, machine.travel_min_mm, machine.travel_max_mm)
    field = deviation(chain, points, np.zeros(3), tables.model(""))[0]

    def residual(applied):
        r = field - deviation(chain, points, np.zeros(3), applied)[0]
        r -= r.mean(axis=0)
        return np.sqrt(np.mean(np.sum(r**2, axis=1))) * 1e3

    assert residual(fit.mean) == pytest.approx(fit.after_um)
    for name in ("EXX", "EYX", "EXZ"):
        for sign in (1, -1):
            positions, values = fit.mean.tables[name]
            nudged = dict(fit.mean.tables)
            nudged[name] = (positions, values + sign * 0.2e-3 * rng.random(len(values)))
            assert residual(type(fit.mean)(tables=nudged)) > fit.after_um


def test_tool_offset_changes_what_is_compensated(machine):
    tables = make_tables({"ECX": [0, 20, 40, 20, 0]})  # yaw of X moves a tool offset in y by t_x
    at_spindle = _fit(CompModel(CROSS, False), tables, machine)
    with_tool = _fit(CompModel(CROSS, False), tables, machine, tool=(100.0, 0.0, 0.0))
    assert at_spindle.before_um < with_tool.before_um
    assert not np.allclose(at_spindle.table("Y", "X")[1], with_tool.table("Y", "X")[1])


def test_directional_tables_carry_the_reversal(machine):
    tables = with_reversal(make_tables({"EXX": [0, 5, 0, 0, 0]}), "EXX", 2.0)
    bidirectional = _fit(CompModel(PITCH, True), tables, machine)
    one_way = _fit(CompModel(PITCH, False), tables, machine)
    forward, reverse = bidirectional.table("X", "X", "+")[1], bidirectional.table("X", "X", "-")[1]
    np.testing.assert_allclose((reverse - forward) * 1e3, 4.0, atol=1e-9)
    assert bidirectional.after_um == pytest.approx(0.0, abs=1e-9)
    assert one_way.after_um == pytest.approx(2.0, rel=1e-6)  # the half reversal stays


def test_volumetric_model_leaves_nothing_and_pitch_warns(machine):
    rng = np.random.default_rng(3)
    tables = make_tables({name: rng.normal(0, 5, 5) for name in ("EYX", "EBX", "EZY")}, EC0Y=10)
    assert fit_for(machine, tables, "isg").after_um == pytest.approx(0.0, abs=1e-9)
    pitch = fit_for(machine, tables, "linuxcnc")
    assert not pitch.removes_enough


def test_remaining_errors_are_the_model_minus_the_tables(machine):
    tables = make_tables({"EXX": [4, 10, 12, 5, 0], "EYX": [0, 3, 0, 0, 0]})
    remaining = remaining_errors(tables, "linuxcnc", machine)
    delta, _ = remaining.motions("X", np.array([100.0]))
    # pitch takes EXX out (up to its value at the reference), leaves EYX
    np.testing.assert_allclose(delta[0] * 1e3, [4.0, 3.0, 0.0], atol=1e-9)


@pytest.mark.parametrize("controller", ["sinumerik", "fanuc", "heidenhain", "linuxcnc", "isg"])
def test_every_controller_formats_the_shared_fit(controller, machine):
    result = compensate(machine, make_tables({"EXX": [0, 5, 3, 1, 0]}), controller)
    assert result.fit.converged and result.files


def test_every_node_of_a_long_table_is_pinned(machine):
    """81 nodes per axis (post writes tables at a quarter of the target spacing): the fit
    must still give every node its value (it once evaluated 31 points per axis at most,
    leaving the nodes between them to a minimum-norm guess)."""
    n = 81
    wave = 5.0 * np.sin(np.linspace(0.0, 9.0 * np.pi, n))
    tables = make_tables({"EXX": wave, "EYY": -wave, "EZZ": 0.5 * wave}, n=n)
    for model in (CompModel(PITCH, False), CompModel(CROSS, False)):
        fit = _fit(model, tables, machine)
        assert fit.converged
        assert fit.after_um == pytest.approx(0.0, abs=1e-9) and fit.before_um > 3.0
        positions, values = fit.table("X", "X")
        np.testing.assert_allclose(values * 1e3, wave - wave[0], atol=1e-9)
