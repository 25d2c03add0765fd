"""The simulated shop, weather station and optical-path interferometer."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim.clock import SimClock
from sim.environment import ShopClimate, SimEnvironment, SimWeatherStation
from tests.sim.test_interferometer import setup
from xmalign.environment import (
    EnvironmentColumns,
    EnvironmentMonitor,
    compensate_linear,
    edlen_index,
)
from xmalign.errors import DeviceTimeoutError, InputError
from xmalign.geometry import line_frame
from xmalign.roles import EnvironmentSource

LAUNCH_MM = np.array([100.0, 100.0, -680.0])


def test_climate_ramps_and_holds() -> None:
    clock = SimClock()
    env = SimEnvironment(clock, ShopClimate.drifting(ramp_s=1000.0))
    assert env.air_temp_c() == pytest.approx(22.0)
    clock.sleep(500.0)
    assert env.material_temp_c() == pytest.approx(22.5)
    assert env.air_pressure_hpa() == pytest.approx(973.5)
    clock.sleep(5000.0)
    assert env.material_temp_c() == pytest.approx(23.0)
    assert 24.7 <= env.air_temp_c() <= 25.3


def test_growth_is_alpha_dt_from_the_reference() -> None:
    clock = SimClock()
    climate = ShopClimate(material_start_c=25.0, material_end_c=25.0)
    env = SimEnvironment(clock, climate, 10.0, reference_mm=(0.0, 0.0, 0.0))
    np.testing.assert_allclose(env.growth_mm([1000.0, 0.0, -500.0]), [0.05, 0.0, -0.025])


def test_interferometer_counts_the_optical_path(machine) -> None:
    xm, cnc, aligned = setup(machine)
    env = SimEnvironment(xm.clock, ShopClimate(air_start_c=24.0, air_end_c=24.0))
    xm.environment = env
    n = float(edlen_index(24.0, 1013.25, 50.0))
    assert xm.read().channels[0] == pytest.approx(n * aligned.distance_mm * 1e3, abs=1e-6)
    xm.zero()
    beam = line_frame(cnc.position + machine.receiver_offset - LAUNCH_MM)
    cnc.position = cnc.position + 100.0 * beam[0]
    assert xm.read().channels[0] == pytest.approx(n * 100.0 * 1e3, abs=1e-3)


def test_station_reads_and_fails_on_command() -> None:
    clock = SimClock()
    station = SimWeatherStation(SimEnvironment(clock), material_sensors=3, seed=1)
    assert isinstance(station, EnvironmentSource)
    reading = station.read()
    assert reading.air_temp_c == pytest.approx(20.0, abs=0.1)
    assert len(reading.material_temp_c) == 3
    station.failed.add("air_humidity_percent")
    assert math.isnan(station.read().air_humidity_percent)
    station.answering = False
    with pytest.raises(DeviceTimeoutError):
        station.read()


def test_monitor_holds_the_last_good_value_and_flags_it() -> None:
    clock = SimClock()
    env = SimEnvironment(clock, ShopClimate.drifting(ramp_s=100.0))
    station = SimWeatherStation(env, material_sensors=2, noise_temp_c=0.0, seed=2)
    monitor = EnvironmentMonitor(station, "station")
    first = monitor.prime()
    assert monitor.columns == (
        "air_temp_c",
        "air_pressure_hpa",
        "air_humidity_percent",
        "material_temp_c",
    )
    assert first.flags == ()
    clock.sleep(50.0)
    station.failed.add("air_temp_c")
    held = monitor.sample()
    assert held.values["air_temp_c"] == first.values["air_temp_c"]
    assert held.values["material_temp_c"] == pytest.approx(22.5)
    assert held.flags == ("air_temp_c held: no reading",)
    station.failed.add("material_temp_c1")  # one of two material sensors: the other one counts
    assert monitor.sample().flags == ("air_temp_c held: no reading",)
    station.answering = False
    lost = monitor.sample()
    assert len(lost.flags) == 4 and "not answering" in lost.flag_text
    assert lost.values["material_temp_c"] == pytest.approx(22.5)


def test_monitor_flags_a_value_the_sensor_cannot_report() -> None:
    clock = SimClock()
    climate = ShopClimate(pressure_start_hpa=1013.0, pressure_end_hpa=1500.0, ramp_s=10.0)
    monitor = EnvironmentMonitor(
        SimWeatherStation(SimEnvironment(clock, climate), noise_pressure_hpa=0.0, seed=3)
    )
    monitor.prime()
    clock.sleep(20.0)
    sample = monitor.sample()
    assert sample.flags == ("air_pressure_hpa held: 1500 out of the sensor's range",)
    assert sample.values["air_pressure_hpa"] == pytest.approx(1013.0, abs=0.5)


def test_monitor_refuses_to_start_without_a_complete_reading() -> None:
    station = SimWeatherStation(SimEnvironment(SimClock()), seed=4)
    station.failed.add("air_pressure_hpa")
    with pytest.raises(InputError, match="no reading from the air_pressure_hpa sensor"):
        EnvironmentMonitor(station, "station").prime()
    station.answering = False
    with pytest.raises(DeviceTimeoutError, match="station: simulated weather station"):
        EnvironmentMonitor(station, "station").prime()


def test_compensation_undoes_the_simulated_air_dead_path_and_growth(machine) -> None:
    # the receiver moves away along the beam while the air heats by 10 K and the machine by 3 K;
    # compensate_linear with the true environment gives the geometric move back
    xm, cnc, aligned = setup(machine, cnc_mm=(600.0, 100.0, -450.0))
    climate = ShopClimate(
        air_start_c=20.0, air_end_c=30.0, material_start_c=21.0, material_end_c=24.0, ramp_s=40.0
    )
    env = SimEnvironment(xm.clock, climate, 11.5, reference_mm=cnc.position.copy())
    xm.environment = env
    xm.zero()
    beam = line_frame(cnc.position + machine.receiver_offset - LAUNCH_MM)[0]
    start = cnc.position.copy()
    commanded, linear, columns = [], [], []
    for step in range(5):
        cnc.position = start + 100.0 * step * beam
        commanded.append(100.0 * step)
        linear.append(xm.read().channels[0] - 100e3 * step)
        columns.append(
            [
                env.air_temp_c(),
                env.air_pressure_hpa(),
                env.air_humidity_percent(),
                env.material_temp_c(),
            ]
        )
        xm.clock.sleep(10.0)
    columns_ = np.array(columns).T
    raw = np.array(linear)
    result = compensate_linear(
        raw, commanded, np.zeros(5, int), EnvironmentColumns(*columns_), 11.5, aligned.distance_mm
    )
    assert np.max(np.abs(raw)) > 100.0  # the uncompensated reading is far off
    np.testing.assert_allclose(result.linear_um, 0.0, atol=1e-6)
    no_dead_path = compensate_linear(
        raw, commanded, np.zeros(5, int), EnvironmentColumns(*columns_), 11.5, 0.0
    )
    assert np.max(np.abs(no_dead_path.linear_um)) > 1.0  # the dead path matters here
