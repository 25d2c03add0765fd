"""Two launch-unit stations end to end on the virtual machine (issue 13, item 2)."""

from __future__ import annotations

from sim.dry_run import DryRunOptions
from sim.two_stations import simulate_two_stations
from trajectories.stations import TARGET_COVERAGE
from xmalign.formats.error_tables import read_error_tables


def test_two_stations_cover_the_travel(reference_machine, tmp_path):
    report = simulate_two_stations(reference_machine, tmp_path, DryRunOptions(seed=2))
    assert min(report.proposal.coverage.values()) >= TARGET_COVERAGE
    second = report.stations[1].plan.plan
    assert [line.id for line in second.lines] == list(report.proposal.line_ids)
    labels = set(report.post.fit.residual_rms)
    assert {"X", "Z", "Z@2"} <= labels
    tables = read_error_tables(tmp_path / "errors.csv")
    assert tables.tables["EZZ"].positions_mm[0] == reference_machine.travel_min_mm[2]
    # issue 13: <= 1.0 um over the whole travel with two stations
    assert report.travel_um <= 1.0
