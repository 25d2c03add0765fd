"""A file whose '-' passes were zeroed again at the turn is recognised and named."""

from __future__ import annotations

import numpy as np
import pytest

from sim.machine import VirtualMachine
from sim.synthetic import SetupDisturbance, measure, six_line_plan
from xmalign.post.datum import rezeroed_runs
from xmalign.post.evaluate import post_process
from xmalign.rigid_body import Chain

BACKLASH_MM = np.array([0.004, 0.003, 0.002])


def _post(machine, rezero: bool):
    plan = six_line_plan(machine, 15, runs=2, bidirectional=True)
    rows = measure(
        plan,
        Chain.parse(machine.chain),
        VirtualMachine(machine, seed=31),
        np.random.default_rng(4),
        backlash_mm=BACKLASH_MM,
        setup=SetupDisturbance(rezero_each_pass=rezero),
    )
    return post_process(machine, plan, rows, "m.csv")


@pytest.fixture(scope="module")
def rezeroed(reference_machine):
    return _post(reference_machine, rezero=True)


def test_a_continued_datum_gives_no_warning(reference_machine):
    result = _post(reference_machine, rezero=False)
    assert result.warnings == []
    assert result.fit.sigma0 < 1.0


def test_rezeroed_minus_passes_are_named_per_line(rezeroed):
    moving = [d for d in rezeroed.lines if len(rezeroed_runs(d)) == 2]
    assert moving, "every line of this machine moves its linear reading by > 5 um"
    named = {w.split()[1] for w in rezeroed.warnings}
    assert named == {d.label for d in moving}
    assert all("re-zeroed" in w and "run 1, 2" in w for w in rezeroed.warnings)
    # what the user would otherwise only see as a reversal far from the backlash
    tables = rezeroed.fit.tables.tables
    reversal = tables["EXX+"].values - tables["EXX-"].values
    assert np.max(np.abs(reversal + BACKLASH_MM[0])) > 0.010
