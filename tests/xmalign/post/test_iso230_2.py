"""ISO 230-2 figures against a hand-computed example."""

from __future__ import annotations

import math

import numpy as np

from xmalign.post.iso230_2 import positioning_figures

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
