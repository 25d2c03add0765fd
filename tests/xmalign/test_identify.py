import math
from dataclasses import replace
from functools import partial

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from sim.identification import SessionImperfections, simulate_session, spread_positions
from sim.imperfections import UnitImperfections
from xmalign import identify as identify_module
from xmalign.errors import GeometryError, InputError
from xmalign.geometry import wrap_angle
from xmalign.identify import (
    METHODS,
    N_INPUTS,
    N_SYSTEMATICS,
    RZ,
    _Model,
    identify,
    observations_from_session,
)


def _noise_free_session(rng, machine, spindle_angle, receiver_offset, offsets=(0.0, 0.0, 0.0)):
    launch = np.array(machine.launch_unit.position_mm) + rng.uniform(-200, 200, 3)
    gamma = rng.uniform(-math.pi, math.pi)
    imperfections = SessionImperfections(
        launch=UnitImperfections(zero_offsets_rad=np.array([0.0, offsets[0]])),
        receiver=UnitImperfections(zero_offsets_rad=np.array([offsets[1], offsets[2], 0.0])),
        distance_noise_mm=0.0,
    )
    truth = imperfections.truth(launch, gamma)
    positions = spread_positions(machine, 8) + rng.uniform(-100, 100, (8, 3))
    session = simulate_session(positions, truth, receiver_offset, spindle_angle, imperfections, rng)
    return session, truth


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    spindle_deg=st.floats(-180, 180),
    offset=st.lists(st.floats(-200, 200), min_size=3, max_size=3),
)
def test_every_method_recovers_a_noise_free_session(reference_machine, seed, spindle_deg, offset):
    rng = np.random.default_rng(seed)
    session, truth = _noise_free_session(
        rng, reference_machine, math.radians(spindle_deg), np.array(offset)
    )
    for method in METHODS:
        result = identify(session, method)
        np.testing.assert_allclose(result.position_mm, truth.launch2mcs_mm, atol=1e-9)
        assert abs(wrap_angle(result.gamma_rad - truth.gamma_rad)) < 1e-9


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_joint_recovers_pose_and_encoder_offsets(reference_machine, seed):
    rng = np.random.default_rng(seed)
    offsets = rng.normal(0, 100e-6, 3)
    session, truth = _noise_free_session(
        rng, reference_machine, 0.0, reference_machine.receiver_offset, offsets
    )
    result = identify(session, "joint")
    assert set(result.offsets_rad) == {"c2", "c3", "c4"}
    np.testing.assert_allclose(result.position_mm, truth.launch2mcs_mm, atol=1e-9)
    assert abs(wrap_angle(result.gamma_rad - truth.gamma_rad)) < 1e-9
    np.testing.assert_allclose(
        [result.offsets_rad[k] for k in ("c2", "c3", "c4")], offsets, atol=1e-12
    )


def _realistic(reference_machine, seed, n=8):
    rng = np.random.default_rng(seed)
    imperfections = SessionImperfections.realistic(rng)
    truth = imperfections.truth(np.array([100.0, 100.0, -680.0]), 0.7)
    session = simulate_session(
        spread_positions(reference_machine, n),
        truth,
        reference_machine.receiver_offset,
        0.0,
        imperfections,
        rng,
    )
    return session, truth


def test_joint_beats_the_seed_method_on_realistic_units(reference_machine):
    errors = {"joint": [], "intersection": []}
    for seed in range(12):
        session, truth = _realistic(reference_machine, seed)
        for method in errors:
            result = identify(session, method)
            errors[method].append(np.linalg.norm(result.position_mm - truth.launch2mcs_mm))
    assert np.sqrt(np.mean(np.square(errors["joint"]))) < 0.5 * np.sqrt(
        np.mean(np.square(errors["intersection"]))
    )


def test_one_bad_alignment_is_detected_and_named(reference_machine):
    session, truth = _realistic(reference_machine, 3)
    bad = session.alignments[5]
    session.alignments[5] = type(bad)(
        bad.machine_mm + np.array([0.0, 0.0, 2.0]),
        bad.launch_rad,
        bad.receiver_rad,
        bad.distance_mm,
    )
    result = identify(session, "joint")
    assert result.outlier == 5
    assert result.alignments[5].excluded
    assert any("alignment 6" in w and "outlier" in w for w in result.warnings)
    assert np.linalg.norm(result.position_mm - truth.launch2mcs_mm) < 0.1


def test_contributions_add_up(reference_machine):
    session, _ = _realistic(reference_machine, 4)
    result = identify(session, "joint")
    shares = [a.share_position for a in result.alignments]
    assert 0.0 < sum(shares) <= 1.0 + 1e-9
    assert all(0.0 <= s <= 1.0 for s in shares)


def test_parallel_beams_are_degenerate(reference_machine):
    session, _ = _realistic(reference_machine, 5)
    positions = np.array([[100.0 + 300 * k, 100.0, -500.0] for k in range(4)])
    imperfections = SessionImperfections()
    truth = imperfections.truth(np.array([-500.0, 100.0, -680.0]), 0.0)
    collinear = simulate_session(positions, truth, [0.0, 0.0, -180.0], 0.0, imperfections)
    for method in ("intersection", "joint"):
        with pytest.raises(GeometryError, match="degenerate"):
            identify(collinear, method)


def test_too_few_alignments_and_missing_distances(reference_machine):
    session, _ = _realistic(reference_machine, 6, n=3)
    session.alignments = session.alignments[:1]
    with pytest.raises(InputError, match="at least 2 alignments"):
        identify(session, "joint", source="s.json")
    session, _ = _realistic(reference_machine, 6, n=4)
    session.alignments = [
        type(a)(a.machine_mm, a.launch_rad, a.receiver_rad) for a in session.alignments
    ]
    with pytest.raises(InputError, match="distance_mm"):
        identify(session, "distance")


def test_weak_geometry_warns_and_offsets_not_separable_are_named(reference_machine):
    rng = np.random.default_rng(7)
    imperfections = SessionImperfections.realistic(rng, with_distance=False)
    truth = imperfections.truth(np.array([100.0, 100.0, -680.0]), 0.2)
    positions = np.array(
        [[1500.0, 700.0, -100.0], [1600.0, 800.0, -100.0], [1550.0, 750.0, -150.0]]
    )
    session = simulate_session(positions, truth, [0, 0, -180.0], 0.0, imperfections, rng)
    result = identify(session, "joint")
    assert result.offsets_not_estimated
    text = " ".join(result.warnings)
    assert "only 3 alignments" in text
    assert "nearly parallel" in text


def test_model_derivatives_match_finite_differences(reference_machine):
    """The casadi Jacobians (per alignment, as assembled) against central differences."""
    session, _ = _realistic(reference_machine, 8, n=5)
    obs = observations_from_session(session)
    rng = np.random.default_rng(8)
    for method, estimated in (("joint", ("c2", "c4")), ("intersection", ()), ("distance", ())):
        model = _Model(method, estimated, obs)
        theta = np.concatenate([[100.0, 100.0, -680.0, 0.7], rng.normal(0, 50e-6, len(estimated))])
        systematics = rng.normal(0, 1e-5, N_SYSTEMATICS)
        e = model.evaluate(theta, systematics)
        for j in range(len(theta)):
            h = np.zeros_like(theta)
            h[j] = 1e-6
            numeric = (
                model.evaluate(theta + h, systematics).residuals
                - model.evaluate(theta - h, systematics).residuals
            ) / 2e-6
            np.testing.assert_allclose(e.d_theta[:, :, j], numeric, rtol=1e-4, atol=1e-6)
        for j in range(N_SYSTEMATICS):
            h = np.zeros(N_SYSTEMATICS)
            h[j] = 1e-6
            numeric = (
                model.evaluate(theta, systematics + h).residuals
                - model.evaluate(theta, systematics - h).residuals
            ) / 2e-6
            np.testing.assert_allclose(e.d_systematics[:, :, j], numeric, rtol=1e-4, atol=1e-6)
        for j in range(N_INPUTS):
            shifted = []
            for sign in (1, -1):
                inputs = obs.inputs.copy()
                inputs[:, j] += sign * 1e-6
                moved = _Model(method, estimated, replace(obs, inputs=inputs))
                shifted.append(moved.evaluate(theta, systematics).residuals)
            numeric = (shifted[0] - shifted[1]) / 2e-6
            np.testing.assert_allclose(e.d_inputs[:, :, j], numeric, rtol=1e-4, atol=1e-6)


def test_the_solver_says_when_it_did_not_converge(reference_machine, monkeypatch):
    session, _ = _realistic(reference_machine, 9)
    assert identify(session, "joint").converged
    monkeypatch.setattr(
        identify_module, "_gauss_newton", partial(identify_module._gauss_newton, max_iterations=1)
    )
    result = identify(session, "joint")
    assert not result.converged and result.iterations == 1
    assert any("did not converge in 1 iterations" in w for w in result.warnings)


def test_stated_region_covers_the_truth_with_machine_errors(reference_machine):
    """Sessions with the machine's errors (position and tool rotation, common and per
    alignment) and beam collimation: the 95 % region holds the truth 90-99 % of the time,
    and the residuals agree with the stated uncertainties (no scaling, no false outlier)."""
    limit = stats.chi2.ppf(0.95, 4)
    covered, scaled, outliers, sessions = 0, 0, 0, 120
    for seed in range(sessions):
        rng = np.random.default_rng(1000 + seed)
        imperfections = SessionImperfections.realistic(rng, with_distance=False)
        truth = imperfections.truth(
            np.array([100.0, 100.0, -680.0]) + rng.uniform(-50, 50, 3), rng.uniform(-3, 3)
        )
        n = (4, 6, 10, 16)[seed % 4]
        positions = spread_positions(reference_machine, n) + rng.uniform(-30, 30, (n, 3))
        positions = np.clip(
            positions, reference_machine.travel_min_mm, reference_machine.travel_max_mm
        )
        session = simulate_session(
            positions, truth, reference_machine.receiver_offset, 0.0, imperfections, rng
        )
        result = identify(session, "joint")
        delta = np.append(
            result.position_mm - truth.launch2mcs_mm, wrap_angle(result.gamma_rad - truth.gamma_rad)
        )
        covered += delta @ np.linalg.solve(result.covariance, delta) <= limit
        scaled += result.covariance_scale > 1.0
        outliers += result.outlier is not None
    assert 0.90 <= covered / sessions <= 0.99
    assert scaled / sessions <= 0.1
    assert outliers / sessions <= 0.05


def test_tool_rotation_is_in_the_model(reference_machine):
    """Turning the tool (receiver mount) by 25 urad shifts the receiver angles, not the launch's."""
    session, truth = _realistic(reference_machine, 10, n=6)
    obs = observations_from_session(session)
    model = _Model("joint", (), obs)
    theta = np.append(truth.launch2mcs_mm, truth.gamma_rad)
    inputs = obs.inputs.copy()
    inputs[:, RZ] = 25e-6
    turned = _Model("joint", (), replace(obs, inputs=inputs)).residuals(theta)
    change = turned - model.residuals(theta)
    np.testing.assert_allclose(change[:, [0, 1, 4]], 0.0, atol=1e-12)
    np.testing.assert_allclose(np.abs(change[:, 2]), 25e-6, rtol=0.05)
