"""ISO 230-2 figures against a hand-computed example."""

from __future__ import annotations

import math

import numpy as np

from xmalign.post.iso230_2 import positioning_figures, runs_note, vdi3441_figures

# two targets, two runs, both directions (um)
UP = {0: [1.0, 3.0], 1: [5.0, 7.0]}
DOWN = {0: [-1.0, 1.0], 1: [2.0, 2.0]}


def _arrays():
    index, sign, run, value = [], [], [], []
    for direction, data in ((1.0, UP), (-1.0, DOWN)):
        for i, values in data.items():
            for j, v in enumerate(values):
                index.append(i), sign.append(direction), run.append(j + 1), value.append(v)
    return np.array(index), np.array(sign), np.array(run), np.array(value)


def test_hand_computed_figures():
    f = positioning_figures("X", *_arrays())
    s = math.sqrt(2.0)  # std of (1, 3), (5, 7), (-1, 1); 0 for (2, 2)
    assert f.runs == 2
    assert math.isclose(f.E_up, 6.0 - 2.0) and math.isclose(f.E_down, 2.0)
    assert math.isclose(f.R_up, 4 * s) and math.isclose(f.R_down, 4 * s)
    assert math.isclose(f.B, 4.0) and math.isclose(f.B_mean, 3.0)
    assert math.isclose(f.E, 6.0 - 0.0)
    assert math.isclose(f.M, 4.0 - 1.0)
    assert math.isclose(f.R, max(2 * s + 2 * s + 2.0, 2 * s + 0 + 4.0, 4 * s))
    assert math.isclose(f.A_up, (6 + 2 * s) - (2 - 2 * s))
    assert math.isclose(f.A, (6 + 2 * s) - (0 - 2 * s))


def test_one_direction_one_run_leaves_the_rest_undefined():
    index, sign, run, value = _arrays()
    keep = (sign > 0) & (run == 1)
    f = positioning_figures("Y", index[keep], sign[keep], run[keep], value[keep])
    assert math.isclose(f.E_up, 4.0)
    assert math.isnan(f.R_up) and math.isnan(f.B) and math.isnan(f.E_down)


# A worked example with the five runs ISO 230-2 asks for, three targets (um).
# By hand, with a = sqrt(0.5) (the n-1 standard deviation of e.g. 0, 1, 2, 1, 1):
#   up:   target 0: 0 1 2 1 1   mean 1, s a     down: target 0: -1 -1 -1 -1 -1  mean -1, s 0
#         target 1: 3 5 4 4 4   mean 4, s a           target 1:  1  3  2  2  2  mean  2, s a
#         target 2: 2 2 2 2 2   mean 2, s 0           target 2:  0  2  1  1  1  mean  1, s a
#   reversal B_i = 2, 2, 1; bidirectional means 0, 3, 1.5
#   ISO 230-2: E↑ = 4-1 = 3, E↓ = 2-(-1) = 3, E = 4-(-1) = 5, M = 3-0 = 3, B = 2, B̄ = 5/3,
#     R↑ = R↓ = 4a, R = max(2+2a, 2+4a, 1+2a, 4a) = 2+4a,
#     A↑ = (4+2a)-(1-2a) = 3+4a, A↓ = (2+2a)-(-1) = 3+2a, A = (4+2a)-(-1) = 5+2a
#   VDI/DGQ 3441: Ps_j = 6(s↑+s↓)/2 = 3a, 6a, 3a -> Ps = 6a; U = 2; Pa = 3;
#     x̄_j ± (U_j+Ps_j)/2 -> [-1-1.5a, 1+1.5a], [2-3a, 4+3a], [1-1.5a, 2+1.5a] -> P = 5+4.5a
FIVE_UP = {0: [0, 1, 2, 1, 1], 1: [3, 5, 4, 4, 4], 2: [2, 2, 2, 2, 2]}
FIVE_DOWN = {0: [-1, -1, -1, -1, -1], 1: [1, 3, 2, 2, 2], 2: [0, 2, 1, 1, 1]}


def _five_runs():
    index, sign, run, value = [], [], [], []
    for direction, data in ((1.0, FIVE_UP), (-1.0, FIVE_DOWN)):
        for i, values in data.items():
            for j, v in enumerate(values):
                index.append(i), sign.append(direction), run.append(j + 1), value.append(v)
    return np.array(index), np.array(sign), np.array(run), np.array(value, dtype=float)


def test_worked_example_with_five_runs():
    a = math.sqrt(0.5)
    f = positioning_figures("X", *_five_runs())
    expected = {
        "E_up": 3.0,
        "E_down": 3.0,
        "E": 5.0,
        "M": 3.0,
        "B": 2.0,
        "B_mean": 5.0 / 3.0,
        "R_up": 4 * a,
        "R_down": 4 * a,
        "R": 2 + 4 * a,
        "A_up": 3 + 4 * a,
        "A_down": 3 + 2 * a,
        "A": 5 + 2 * a,
    }
    for name, value in expected.items():
        assert math.isclose(getattr(f, name), value, abs_tol=1e-12), name
    assert f.runs == 5 and runs_note(f) is None


def test_worked_example_vdi_3441():
    a = math.sqrt(0.5)
    index, sign, _, value = _five_runs()
    v = vdi3441_figures("X", index, sign, value)
    assert math.isclose(v.Ps, 6 * a) and math.isclose(v.U, 2.0) and math.isclose(v.Pa, 3.0)
    assert math.isclose(v.P, 5 + 4.5 * a)


def test_fewer_than_five_runs_are_noted_and_one_direction_has_no_vdi_figures():
    f = positioning_figures("X", *_arrays())
    assert "2 run(s), ISO 230-2 asks for 5" in runs_note(f)
    index, sign, run, value = _five_runs()
    up = sign > 0
    assert math.isnan(vdi3441_figures("X", index[up], sign[up], value[up]).P)
