import numpy as np
import pytest

from xmalign.errors import InputError
from xmalign.rigid_body import Chain, ErrorTables, deviation, error_axis, squareness_deviation


def test_chain_parsing_and_lever_arm_axes():
    fyxz = Chain.parse("FYXZ")
    assert fyxz.workpiece == () and fyxz.tool == ("Y", "X", "Z")
    assert fyxz.lever_arm_axes("Y") == ("X", "Z")
    assert fyxz.lever_arm_axes("X") == ("Z",)
    assert fyxz.lever_arm_axes("Z") == ()
    xfyz = Chain.parse("xfyz")
    assert xfyz.workpiece == ("X",) and xfyz.tool == ("Y", "Z")
    assert xfyz.lever_arm_axes("X") == ("Y", "Z", "X")
    yxfz = Chain.parse("YXFZ")
    assert yxfz.lever_arm_axes("Y") == ("Z", "Y", "X")
    assert yxfz.lever_arm_axes("X") == ("Z", "X")
    with pytest.raises(InputError, match="FXXZ"):
        Chain.parse("FXXZ")


def test_lever_arms_add_the_tool_offset():
    arms = Chain.parse("FYXZ").lever_arms([[100.0, 200.0, -50.0]], [0, 0, -180])
    np.testing.assert_allclose(arms["Y"], [[100.0, 0.0, -230.0]])
    np.testing.assert_allclose(arms["X"], [[0.0, 0.0, -230.0]])
    np.testing.assert_allclose(arms["Z"], [[0.0, 0.0, -180.0]])


def test_squareness_signs_follow_the_spec():
    dp = squareness_deviation([[0.0, 100.0, 0.0], [0.0, 0.0, 100.0]], [1e-5, 2e-5, 3e-5])
    np.testing.assert_allclose(dp[0], [-100 * 1e-5, 0, 0])  # y along Y: -y·EC0Y in X
    np.testing.assert_allclose(dp[1], [100 * 3e-5, -100 * 2e-5, 0])  # z: +z·EB0Z, -z·EA0Z


def test_deviation_adds_translation_and_abbe_terms():
    tables = ErrorTables(
        tables={
            "EXX": (np.array([0.0, 1000.0]), np.array([0.0, 0.010])),
            "EBX": (np.array([0.0, 1000.0]), np.array([0.0, 1e-4])),
        }
    )
    dp, rotation = deviation(Chain.parse("FYXZ"), [[500.0, 0.0, 0.0]], [0, 0, -100], tables)
    # EBX (rotation about Y) with lever arm (0, 0, -100): eps x r = (0, 5e-5, 0) x (0, 0, -100)
    np.testing.assert_allclose(dp[0], [0.005 + 5e-5 * -100, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(rotation[0], [0.0, 5e-5, 0.0])


def test_error_axis():
    assert error_axis("EZY") == "Y"
    with pytest.raises(InputError):
        error_axis("EXW")
