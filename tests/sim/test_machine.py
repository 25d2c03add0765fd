import numpy as np
import pytest

from sim.machine import ErrorAmplitudes, VirtualMachine
from xmalign.errors import OutOfRangeError
from xmalign.formats.error_tables import read_error_tables
from xmalign.machine import parse_machine
from xmalign.rigid_body import MOTION_NAMES, deviation


def test_seeded_and_sized(machine):
    a, b = VirtualMachine(machine, seed=3), VirtualMachine(machine, seed=3)
    x = np.linspace(0, 2000, 50)
    np.testing.assert_array_equal(a.motions("X", x)[0], b.motions("X", x)[0])
    assert not np.allclose(VirtualMachine(machine, seed=4).motions("X", x)[0], a.motions("X", x)[0])
    truth = a.truth_tables(100.0)
    exx = truth.tables["EXX"].values
    assert 1e-3 < np.ptp(exx) < 0.5  # tens of um over the travel (mm)
    assert 1e-6 < np.ptp(truth.tables["EAX"].values) < 5e-4


def test_travel_is_enforced(machine):
    vm = VirtualMachine(machine, seed=1)
    with pytest.raises(OutOfRangeError, match="outside the travel"):
        vm.actual_functional_point([2000.5, 0, 0], [1, 1, 1], [0, 0, 0])
    with pytest.raises(OutOfRangeError):
        vm.tool_pose([0, -1, 0], [0, 0, 0])


def test_table_conventions(machine):
    truth = VirtualMachine(machine, seed=2).truth_tables(100.0)
    assert set(truth.tables) == set(MOTION_NAMES)
    for name, table in truth.tables.items():
        assert table.values[0] == 0.0
        if name[1] != name[2] and name[1] in "XYZ":  # straightness
            assert table.values[-1] == pytest.approx(0.0, abs=1e-15)
    assert truth.tables["EXY"].positions_mm[-1] == 1500.0


@pytest.mark.parametrize("chain", ["FYXZ", "XFYZ", "YFXZ", "FXYZ", "ZYXF"])
def test_slopes_moved_to_squareness_are_a_rigid_motion(machine, chain):
    """Straightness slopes only: tables + squareness reproduce the truth up to a rigid motion."""
    motions = {name: (0, 0, 0.5, 0, 0, 1, 0, 0) for name in MOTION_NAMES}
    for name in ("EYX", "EZX", "EXY", "EZY", "EXZ", "EYZ"):
        motions[name] = (0, 40, 0.5, 0, 0, 1, 0, 0)
    setup = parse_machine({**machine.model_dump(), "chain": chain})
    vm = VirtualMachine(setup, ErrorAmplitudes(motions=motions), seed=5)
    tables = vm.truth_tables(250.0).model()
    rng = np.random.default_rng(0)
    points = rng.uniform(setup.travel_min_mm, setup.travel_max_mm, (200, 3))
    difference = (
        deviation(vm.chain, points, [0, 0, 0], vm)[0]
        - deviation(vm.chain, points, [0, 0, 0], tables)[0]
    )
    # fit difference = c + omega x p
    rows = []
    for p in points:
        rows.append(
            np.hstack(
                [np.eye(3), -np.array([[0, -p[2], p[1]], [p[2], 0, -p[0]], [-p[1], p[0], 0]])]
            )
        )
    a = np.vstack(rows)
    solution, *_ = np.linalg.lstsq(a, difference.ravel(), rcond=None)
    assert np.abs(a @ solution - difference.ravel()).max() < 1e-9


def test_backlash_gives_directional_tables_and_csv(machine, tmp_path):
    amplitudes = ErrorAmplitudes(backlash_um=(4.0, 0.0, 2.0), repeatability_um=0.0)
    vm = VirtualMachine(machine, amplitudes, seed=1)
    path = tmp_path / "truth.csv"
    vm.write_truth_tables(str(path), 100.0)
    read = read_error_tables(path)
    assert {"EXX+", "EXX-", "EZZ+", "EZZ-", "EYY"} <= set(read.tables)
    np.testing.assert_allclose(
        read.tables["EXX-"].values - read.tables["EXX+"].values, 4e-3, atol=1e-7
    )
    forward, _ = vm.actual_functional_point([500, 500, -100], [1, 1, 1], [0, 0, 0])
    reverse, _ = vm.actual_functional_point([500, 500, -100], [-1, 1, -1], [0, 0, 0])
    np.testing.assert_allclose(reverse - forward, [4e-3, 0, 2e-3], atol=1e-12)
    for name in ("EC0Y", "EA0Z", "EB0Z"):
        assert read.squareness[name][0] == pytest.approx(
            vm.truth_tables(100.0).squareness[name][0], abs=1e-10
        )


def test_tool_pose_keeps_noise_at_standstill(machine):
    vm = VirtualMachine(machine, ErrorAmplitudes(repeatability_um=1.0), seed=1)
    first = vm.tool_pose([100, 100, -100], [0, 0, -180])[0]
    np.testing.assert_array_equal(first, vm.tool_pose([100, 100, -100], [0, 0, -180])[0])
    vm.tool_pose([200, 100, -100], [0, 0, -180])
    again = vm.tool_pose([100, 100, -100], [0, 0, -180])[0]
    assert not np.array_equal(first, again)
    assert np.abs(first - again).max() < 10e-3


def test_only_the_axes_that_move_draw_new_repeatability_noise(machine):
    vm = VirtualMachine(machine, ErrorAmplitudes(scale=0.0, repeatability_um=1.0), seed=2)
    first = vm.tool_pose([100, 100, -100], [0, 0, 0])[0] - [100, 100, -100]
    second = vm.tool_pose([300, 100, -100], [0, 0, 0])[0] - [300, 100, -100]
    assert second[0] != first[0]
    np.testing.assert_array_equal(second[1:], first[1:])
