"""Refractive index of air, material normalisation, dead path and drift (xmalign.environment)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from xmalign.environment import (
    DRIFT_RUN,
    EnvironmentColumns,
    air_index,
    beam_geometry,
    check_sensor,
    ciddor_index,
    compensate_linear,
    compensate_station,
    datum_rows,
    edlen_index,
    line_drift,
    material_um,
    out_of_range,
    saturation_vapour_pressure_pa,
    summarise,
)
from xmalign.errors import InputError
from xmalign.formats.measurements import MeasurementRow
from xmalign.formats.plan import Plan, PlanLine

# Reference values: the equations of the NIST Engineering Metrology Toolbox
# ("Index of Refraction of Air", Stone & Zimmerman, Appendix A) as evaluated by
# the independent `ref_index` package (P. H. Nair, PyPI `ref_index`, README
# examples): vacuum wavelength 633 nm, 101 325 Pa, 450 ppm CO2.
NIST_EQUATIONS = [
    # method, t / °C, RH / %, n
    ("ciddor", 20.0, 20.0, 1.0002716285340578),
    ("edlen", 20.0, 20.0, 1.0002716291691649),
    ("edlen", 20.0, 80.0, 1.0002711197635226),
    ("ciddor", 20.0, 80.0, 1.0002711183472626),
    ("edlen", 60.0, 80.0, 1.0002339748542823),
    ("ciddor", 60.0, 80.0, 1.0002340241754055),
]


@pytest.mark.parametrize(("method", "temp_c", "humidity", "expected"), NIST_EQUATIONS)
def test_index_matches_the_nist_equations(
    method: str, temp_c: float, humidity: float, expected: float
) -> None:
    n = air_index(temp_c, 1013.25, humidity, method, wavelength_nm=633.0)  # type: ignore[arg-type]
    assert float(n) == pytest.approx(expected, abs=1e-12)


@pytest.mark.parametrize(
    ("temp_c", "pressure_kpa", "humidity"),
    [(20.0, 101.325, 50.0), (24.0, 97.0, 50.0), (15.0, 100.0, 20.0), (30.0, 102.0, 80.0)],
)
def test_index_agrees_with_the_nist_shop_floor_formula(
    temp_c: float, pressure_kpa: float, humidity: float
) -> None:
    # NIST toolbox, Appendix B: n = 1 + 7.86e-4 p/(273 + t) - 1.5e-11 RH (t² + 160),
    # p in kPa, stated to agree with the full equations to about 5e-8 in shop conditions.
    shop = 1 + 7.86e-4 * pressure_kpa / (273 + temp_c) - 1.5e-11 * humidity * (temp_c**2 + 160)
    assert float(edlen_index(temp_c, pressure_kpa * 10, humidity)) == pytest.approx(shop, abs=5e-8)


def test_edlen_and_ciddor_agree_in_a_shop() -> None:
    # NIST (section VII): the two agree to about 1e-8 in ordinary laboratory air
    t, p, h = np.meshgrid([15.0, 20.0, 25.0, 30.0], [950.0, 1013.25, 1050.0], [10.0, 50.0, 90.0])
    assert np.max(np.abs(edlen_index(t, p, h) - ciddor_index(t, p, h))) < 1e-8


def test_the_issue_example_shop_is_about_2_6e_minus_4_off_vacuum() -> None:
    assert float(edlen_index(24.0, 970.0, 50.0)) - 1 == pytest.approx(2.56e-4, abs=1e-6)


def test_saturation_vapour_pressure_at_known_points() -> None:
    # IAPWS: 2339.3 Pa at 20 °C, 611.657 Pa at the triple point (ice branch), 12352 Pa at 50 °C
    values = saturation_vapour_pressure_pa([20.0, 0.01, 50.0, -10.0])
    assert values[0] == pytest.approx(2339.2, abs=0.5)
    assert values[1] == pytest.approx(611.66, abs=0.1)
    assert values[2] == pytest.approx(12352, abs=5)
    assert values[3] == pytest.approx(259.9, abs=0.5)  # over ice


def test_unknown_method_is_refused() -> None:
    with pytest.raises(InputError, match="ciddor"):
        air_index(20, 1013.25, 50, "smith")  # type: ignore[arg-type]


def test_sensor_limits() -> None:
    assert list(out_of_range("air_pressure_hpa", [599.0, 600.0, 1100.0, 1101.0, np.nan])) == [
        True,
        False,
        False,
        True,
        True,
    ]
    with pytest.raises(InputError, match=r"station: air_temp_c 61 .* \(-20 to 60\)"):
        check_sensor("air_temp_c", 61.0, "station")
    assert check_sensor("air_humidity_percent", 100.0, "station") == 100.0


def test_material_normalisation_subtracts_alpha_dt_l() -> None:
    # 11.5 ppm/K, 3 K above 20 °C over 1700 mm: 58.65 um (the issue's "60 um")
    assert float(material_um(1700.0, 23.0, 11.5)) == pytest.approx(58.65)


def _optical_reading(
    geometric_um: np.ndarray, beam0_mm: float, sign: float, n: np.ndarray, n0: float
) -> np.ndarray:
    beam_um = beam0_mm * 1e3 + sign * geometric_um
    return n * beam_um - n0 * beam0_mm * 1e3


@given(
    st.floats(15.0, 30.0),
    st.floats(15.0, 30.0),
    st.floats(900.0, 1050.0),
    st.sampled_from([1.0, -1.0]),
    st.floats(100.0, 2000.0),
)
def test_compensation_recovers_the_geometric_displacement(
    t0: float, t1: float, pressure: float, sign: float, dead_mm: float
) -> None:
    commanded_mm = np.array([0.0, 100.0, 200.0, 300.0])
    error_um = np.array([0.0, 1.5, -2.0, 3.0])
    air = np.linspace(t0, t1, 4)
    n = edlen_index(air, pressure, 40.0)
    material = np.full(4, 22.0)
    expansion = material_um(commanded_mm, material, 11.5)
    geometric = commanded_mm * 1e3 + error_um + expansion
    reading = _optical_reading(geometric, dead_mm, sign, n, float(n[0]))
    linear = sign * reading - commanded_mm * 1e3
    environment = EnvironmentColumns(air, np.full(4, pressure), np.full(4, 40.0), material)
    result = compensate_linear(
        linear, commanded_mm, np.zeros(4, int), environment, 11.5, dead_mm, sign
    )
    np.testing.assert_allclose(result.linear_um, error_um, atol=1e-6)
    assert result.air and result.material


def test_without_columns_nothing_is_changed_and_the_note_says_so() -> None:
    linear = np.array([0.0, 1.0, 2.0])
    result = compensate_linear(linear, [0, 100, 200], [0, 0, 0], EnvironmentColumns(), 11.5)
    np.testing.assert_array_equal(result.linear_um, linear)
    assert "already air-compensated" in result.note and "at 20 °C" in result.note


def test_datum_rows_per_run() -> None:
    run = np.array([1, 1, 1, 1, 2, 2, 2, 2])
    sign = np.array([1, 1, -1, -1, 1, 1, -1, -1])
    index = np.array([0, 1, 1, 0, 0, 1, 1, 0])
    assert list(datum_rows(run, sign, index)) == [0, 0, 0, 0, 4, 4, 4, 4]
    # a run resumed after its datum row falls back to its first row
    assert list(datum_rows([3, 3], [-1, -1], [1, 0])) == [0, 0]


def test_beam_geometry() -> None:
    assert beam_geometry([400.0, 2100.0]) == (400.0, 1.0)
    assert beam_geometry([2100.0, 400.0]) == (2100.0, -1.0)
    assert beam_geometry(None) == (0.0, 1.0)


def test_drift_and_limit() -> None:
    check = line_drift("X", [1.1, 1.3], limit_um=1.0)
    assert check.drift_um == pytest.approx(1.2)
    assert check.exceeded
    assert "exceeds the machine file's limit 1 um" in check.message()
    assert not line_drift("Y", [0.5], limit_um=1.0).exceeded
    assert not line_drift("Y", [5.0]).exceeded
    with pytest.raises(InputError, match="line Z"):
        line_drift("Z", [])


def test_summary() -> None:
    summary = summarise(EnvironmentColumns(air_temp_c=np.array([22.0, 23.0, 24.0])))
    assert summary["air_temp_c"].mean == pytest.approx(23.0)
    assert np.isnan(summary["material_temp_c"].mean)


def _plan(beam_distance_mm: list[float]) -> Plan:
    line = PlanLine(
        id="X",
        start_mm=np.zeros(3),
        end_mm=np.array([300.0, 0.0, 0.0]),
        frame=np.eye(3),
        launch_rad=np.zeros(2),
        receiver_rad=np.zeros(3),
        targets_mm=np.array([0.0, 100.0, 200.0, 300.0]),
        runs=2,
        extra={"beam_distance_mm": beam_distance_mm},
    )
    return Plan("m", np.zeros(3), 0.0, [line])


def _row(run: int, index: int, linear_um: float) -> MeasurementRow:
    return MeasurementRow(
        "X",
        run,
        "+",
        index,
        100.0 * index,
        np.array([100.0 * index, 0, 0]),
        np.array([linear_um, 0, 0, 0, 0, 0]),
    )


def test_station_compensation_with_a_drift_check() -> None:
    plan = _plan([500.0, 800.0])
    error_um = np.array([0.0, 1.0, 2.0, 1.0])
    air = {"air_temp_c": 20.0, "air_pressure_hpa": 1013.25, "air_humidity_percent": 50.0}
    n = float(edlen_index(20.0, 1013.25, 50.0))
    rows, environments = [], []
    for run in (1, 2):
        for index in range(4):
            geometric_um = 100e3 * index + error_um[index]
            linear = n * geometric_um - 100e3 * index  # optical path, air constant
            rows.append(_row(run, index, linear))
            environments.append({**air, "material_temp_c": 20.0})
    # the drift check: the first target read 1.5 um (optical) after the last run
    rows.append(_row(DRIFT_RUN, 0, 1.5 * n))
    environments.append({**air, "material_temp_c": 20.0})
    result = compensate_station(plan, rows, environments, 11.5, drift_limit_um=1.0)
    assert len(result.rows) == 8
    np.testing.assert_allclose(
        [r.channels[0] for r in result.rows], np.tile(error_um, 2), atol=1e-9
    )
    assert result.drift[0].drift_um == pytest.approx(1.5)
    assert result.drift[0].exceeded
    assert result.environment["X"]["air_temp_c"].mean == pytest.approx(20.0)
    assert "modified Edlén" in result.note


def test_station_without_environment_is_left_alone() -> None:
    rows = [_row(1, i, 0.5 * i) for i in range(4)]
    result = compensate_station(_plan([500.0, 800.0]), rows, [{}] * 4, 11.5)
    assert [r.channels[0] for r in result.rows] == [0.0, 0.5, 1.0, 1.5]
    assert result.drift == []
    assert "already air-compensated" in result.note


def test_record_info_of_a_compensation() -> None:
    from xmalign.report import RecordInfo

    rows = [_row(1, i, 0.5 * i) for i in range(4)]
    env = {"air_temp_c": 21.0, "air_pressure_hpa": 1000.0, "air_humidity_percent": 40.0}
    compensation = compensate_station(_plan([500.0, 800.0]), rows, [env] * 4, 11.5)
    info = RecordInfo.of_compensation(compensation, operator="me")
    assert info.operator == "me" and "modified Edlén" in info.compensation
    assert info.environment["X"]["air_temp_c"].max == 21.0
    assert "already compensated" in RecordInfo.of_compensation(None).compensation
