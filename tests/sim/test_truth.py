"""Simulator truth comes back from the setup that made it (issue 23, item 1): the Monte
Carlo study neither replays the order of the setup's random draws nor builds a setup
a second time to learn what it measured."""

from __future__ import annotations

import numpy as np

from sim.dry_run import placement, virtual_setup
from xmalign.formats.error_tables import read_error_tables


def test_the_placement_is_the_virtual_setups(reference_machine):
    for seed in (0, 1, 7):
        placed = placement(reference_machine, seed)
        world = virtual_setup(reference_machine, seed).world
        np.testing.assert_array_equal(placed.launch2mcs_mm, world.launch2mcs_mm)
        assert placed.gamma_rad == world.gamma_rad


def test_the_dry_run_report_carries_the_machine_it_measured(dry_run_of_seed):
    report, folder = dry_run_of_seed(2, "truth")
    written = read_error_tables(folder / "truth.csv")
    carried = report.truth.truth_tables(50.0)
    for name, table in written.tables.items():
        np.testing.assert_allclose(
            carried.tables[name].values, table.values, atol=1e-7
        )  # 0.1 nm in the file
