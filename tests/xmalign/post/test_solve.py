"""The error-table fit: reproduction of a known machine, conventions, backlash, GUM, rank."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.stats

from sim.machine import ErrorAmplitudes, VirtualMachine
from sim.synthetic import SetupDisturbance, measure, six_line_plan
from xmalign.errors import GeometryError, InputError
from xmalign.machine import Machine
from xmalign.post.compare import grid_points, volumetric_rms_um
from xmalign.post.evaluate import post_process
from xmalign.rigid_body import Chain, ErrorTables

BACKLASH_MM = np.array([0.004, 0.003, 0.002])


def _machine(reference: Machine, **changes: object) -> Machine:
    return reference.model_copy(update=changes)


def _fit(machine: Machine, truth: VirtualMachine, seed: int, n: int = 40, **plan: object):
    layout = six_line_plan(machine, n, **plan)
    rows = measure(
        layout,
        Chain.parse(machine.chain),
        truth,
        np.random.default_rng(seed),
        backlash_mm=BACKLASH_MM,
    )
    return post_process(machine, layout, rows, "synthetic.csv")


@pytest.fixture(scope="module")
def truth(reference_machine: Machine) -> VirtualMachine:
    return VirtualMachine(reference_machine, seed=11)


@pytest.fixture(scope="module")
def bidirectional(reference_machine: Machine, truth: VirtualMachine):
    return _fit(reference_machine, truth, seed=5)


def _rms(machine: Machine, model, truth) -> float:
    points = grid_points(machine.travel_min_mm, machine.travel_max_mm, 6)
    return volumetric_rms_um(Chain.parse(machine.chain), points, model, truth)


def test_reproduces_a_known_machine(reference_machine, truth, bidirectional):
    assert _rms(reference_machine, ErrorTables(), truth) > 10.0  # tens of um to reproduce
    assert _rms(reference_machine, bidirectional.fit.tables.model(""), truth) <= 1.0


@pytest.mark.parametrize(
    ("chain", "offset_mm", "spindle_deg"),
    [("XFYZ", [0.0, 0.0, -180.0], 0.0), ("FYXZ", [60.0, -40.0, -300.0], 30.0)],
)
def test_abbe_offsets_and_chains(reference_machine, chain, offset_mm, spindle_deg):
    machine = _machine(
        reference_machine, chain=chain, receiver_offset_mm=offset_mm, spindle_angle_deg=spindle_deg
    )
    truth = VirtualMachine(machine, seed=23)
    result = _fit(machine, truth, seed=2, n=30, runs=1, bidirectional=False)
    assert _rms(machine, result.fit.tables.model(""), truth) <= 1.0


def test_table_conventions(bidirectional):
    tables = bidirectional.fit.tables.tables
    for name in ("EXX", "EAX", "ECY", "EZZ"):
        assert tables[name].values[0] == 0.0 and tables[name].u95[0] == 0.0
    for name in ("EYX", "EZX", "EXY", "EZY", "EXZ", "EYZ"):
        assert tables[name].values[0] == 0.0 and tables[name].values[-1] == 0.0
        assert np.all(tables[name].u95[1:-1] > 0.0)
    assert set(bidirectional.fit.tables.squareness) == {"EC0Y", "EA0Z", "EB0Z"}


def test_forward_and_reverse_tables_recover_the_backlash(bidirectional):
    tables = bidirectional.fit.tables.tables
    for i, name in enumerate(("EXX", "EYY", "EZZ")):
        reversal = tables[name + "+"].values - tables[name + "-"].values
        assert abs(np.mean(reversal) + BACKLASH_MM[i]) < 0.2e-3
        assert np.max(np.abs(reversal + BACKLASH_MM[i])) < 1.0e-3
        assert np.allclose(
            0.5 * (tables[name + "+"].values + tables[name + "-"].values), tables[name].values
        )


def test_setup_terms_and_residuals_are_reported(bidirectional):
    assert [s.line_id for s in bidirectional.fit.setup] == ["X", "Y", "Z", "XY", "YZ", "XZ"]
    assert all(len(s.linear_offset_um) == 2 for s in bidirectional.fit.setup)
    for rms in bidirectional.fit.residual_rms.values():
        assert np.all(rms < 2.0)  # noise level of the synthetic channels
    assert 0.2 < bidirectional.fit.sigma0 < 1.0


def test_expanded_uncertainty_follows_the_channel_uncertainties(reference_machine, truth):
    base = _fit(reference_machine, truth, seed=7, n=20, runs=1, bidirectional=False)
    doubled = reference_machine.uncertainty.model_copy(
        update={
            name: 2 * getattr(reference_machine.uncertainty, name)
            for name in (
                "channel_linear_um",
                "channel_straightness_um",
                "channel_angle_urad",
                "channel_roll_urad",
            )
        }
    )
    machine = _machine(reference_machine, uncertainty=doubled)
    scaled = _fit(machine, truth, seed=7, n=20, runs=1, bidirectional=False)
    a, b = base.fit.tables.tables["EXX"].u95, scaled.fit.tables.tables["EXX"].u95
    assert np.allclose(b[1:], 2 * a[1:], rtol=1e-6)
    assert "EXX+" not in base.fit.tables.tables


#: Repeated measurements of the u95 check: the scatter's degrees of freedom are one fewer.
_REPEATS = 16


def _scatter_over_predicted(machine: Machine, truth: VirtualMachine, inflate: float) -> float:
    """RMS over EXX's points of (scatter of repeated measurements) / (u95 / 2).

    The synthetic noise is the machine file's channel uncertainty and the machine
    repeats perfectly, so u95 / 2 should be the scatter itself; ``inflate`` scales the
    reported u95 (a check that the test fails for a u95 that overstates it).
    """
    u = machine.uncertainty
    matched = SetupDisturbance(
        noise=(
            u.channel_linear_um,
            u.channel_straightness_um,
            u.channel_straightness_um,
            u.channel_roll_urad,
            u.channel_angle_urad,
            u.channel_angle_urad,
        ),
        repeatability_um=0.0,
    )
    layout = six_line_plan(machine, 15, runs=1, bidirectional=False)
    chain = Chain.parse(machine.chain)
    tables = [
        post_process(
            machine,
            layout,
            measure(layout, chain, truth, np.random.default_rng(s), setup=matched),
            "synthetic.csv",
        ).fit.tables.tables["EXX"]
        for s in range(_REPEATS)
    ]
    values = np.array([t.values[1:] for t in tables])
    predicted = np.mean([t.u95[1:] for t in tables], axis=0) * inflate / 2
    return float(np.sqrt(np.mean(values.var(axis=0, ddof=1) / predicted**2)))


def _chi_interval(probability: float) -> tuple[float, float]:
    """Where scatter / sigma lies with ``probability`` for _REPEATS repeats, taking the
    points as one (fully correlated: the widest interval the pooling can have)."""
    dof = _REPEATS - 1
    tail = (1 - probability) / 2
    low, high = scipy.stats.chi2.ppf([tail, 1 - tail], dof)
    return float(np.sqrt(low / dof)), float(np.sqrt(high / dof))


@pytest.mark.parametrize("inflate", [1.0, 3.0])
def test_u95_covers_the_scatter_of_repeated_measurements(reference_machine, truth, inflate):
    """GUM check from both sides: the scatter of EXX over repeated measurements is u95 / 2
    within the chi-square interval of the repeats (99.8 %), neither above (u95 too small)
    nor below (u95 overstating it); a u95 three times too large falls outside."""
    ratio = _scatter_over_predicted(reference_machine, truth, inflate)
    low, high = _chi_interval(0.998)
    assert (low <= ratio <= high) == (inflate == 1.0), (ratio, low, high)


@pytest.mark.parametrize(
    ("missing", "named"),
    [
        (("XY", "YZ", "XZ"), "EC0Y, EA0Z, EB0Z (they trade with the setup terms of lines Y, Z)"),
        (("YZ", "XZ"), "EA0Z, EB0Z (they trade with the setup terms of line Z)"),
        (("XY",), "EC0Y (they trade with the setup terms of lines Y, YZ)"),
    ],
)
def test_without_diagonals_the_squareness_is_refused(reference_machine, truth, missing, named):
    """The message names the undetermined errors whichever null-space basis the BLAS returns."""
    layout = six_line_plan(reference_machine, 10, runs=1, bidirectional=False)
    layout.lines = [line for line in layout.lines if line.id not in missing]
    rows = measure(layout, Chain.parse("FYXZ"), truth, np.random.default_rng(0))
    with pytest.raises(GeometryError) as caught:
        post_process(reference_machine, layout, rows, "m.csv")
    assert str(caught.value).startswith(f"the lines cannot determine {named};")


def test_a_missing_axis_line_is_named(reference_machine, truth):
    layout = six_line_plan(reference_machine, 10, runs=1, bidirectional=False)
    layout.lines = [line for line in layout.lines if line.id != "Y"]
    rows = measure(layout, Chain.parse("FYXZ"), truth, np.random.default_rng(0))
    with pytest.raises(InputError, match="no line along Y"):
        post_process(reference_machine, layout, rows, "m.csv")


def test_a_perfect_machine_gives_zero_tables(reference_machine):
    perfect = VirtualMachine(reference_machine, ErrorAmplitudes(scale=0.0), seed=1)
    layout = six_line_plan(reference_machine, 10, runs=1, bidirectional=False)
    rows = measure(layout, Chain.parse("FYXZ"), perfect, np.random.default_rng(3))
    tables = post_process(reference_machine, layout, rows, "m.csv").fit.tables
    values = np.concatenate([t.values for t in tables.tables.values()])
    u95 = np.concatenate([t.u95 for t in tables.tables.values()])
    assert np.all(np.abs(values) <= 2 * u95 + 1e-12)
    assert np.mean(np.abs(values) <= u95 + 1e-12) >= 0.9


def _rotating_null_space(eigh, seed: int):
    """``eigh`` that returns another orthonormal basis of the null space."""
    rng = np.random.default_rng(seed)

    def rotated(matrix):
        values, vectors = eigh(matrix)
        null = values <= 1e-9 * values[-1]
        turn, _ = np.linalg.qr(rng.normal(size=(null.sum(), null.sum())))
        vectors[:, null] = vectors[:, null] @ turn
        return values, vectors

    return rotated


def test_the_undetermined_message_does_not_depend_on_the_null_space_basis(
    reference_machine, truth, monkeypatch
):
    """Another BLAS returns another basis of the null space: the same errors are named."""
    layout = six_line_plan(reference_machine, 10, runs=1, bidirectional=False)
    layout.lines = layout.lines[:3]
    rows = measure(layout, Chain.parse("FYXZ"), truth, np.random.default_rng(0))
    messages = []
    eigh = np.linalg.eigh
    for seed in (None, 1, 2):
        if seed is not None:
            monkeypatch.setattr(np.linalg, "eigh", _rotating_null_space(eigh, seed))
        with pytest.raises(GeometryError) as caught:
            post_process(reference_machine, layout, rows, "m.csv")
        messages.append(str(caught.value))
    assert messages[0] == messages[1] == messages[2]


def test_the_weights_follow_the_scatter_of_each_channel(reference_machine, truth):
    layout = six_line_plan(reference_machine, 30)
    noise = (0.5, 0.5, 0.5, 0.05, 0.05, 0.05)  # um, urad: positions scatter, angles hardly
    rows = measure(
        layout,
        Chain.parse(reference_machine.chain),
        truth,
        np.random.default_rng(5),
        setup=SetupDisturbance(noise=noise),
    )
    fit = post_process(reference_machine, layout, rows, "synthetic.csv").fit
    scatter = fit.channel_scatter * np.array([1e3, 1e3, 1e3, 1e6, 1e6, 1e6])
    np.testing.assert_allclose(scatter, noise, rtol=0.15)
