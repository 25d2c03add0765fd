"""The controller files xmalign writes against published examples (examples/README.md).

- ``linuxcnc_screwcompX.dat``: LinuxCNC 2.9's own ``COMP_FILE`` sample
  (``docs/examples/sample-configs/sim/screwcompX.dat``, Debian ``linuxcnc-uspace``),
  copied unchanged.
- ``sinumerik_k3_eec_example.ini``: the ``%_N_AX_EEC_INI`` example of the
  SINUMERIK 840D sl Function Manual Extended Functions, K3 "Compensations",
  4.4.2.3 "Example" (6FC5397-1BP40-3BA1, 03/2013, p. 242), points 3 .. 799 left out.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from tests.xmalign.comp.conftest import make_machine, make_tables, with_reversal
from xmalign.comp import compensate

EXAMPLES = Path(__file__).parent / "examples"
NUMBER = r"[-+]?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?"


def _comp_file_rows(text: str) -> np.ndarray:
    """A type-0 COMP_FILE as LinuxCNC reads it: 'nominal forward reverse' per line, (N, 3)."""
    rows = []
    for line in text.splitlines():
        if line.strip():
            assert re.fullmatch(rf"\s*{NUMBER}\s+{NUMBER}\s+{NUMBER}\s*", line), line
            rows.append([float(v) for v in line.split()])
    return np.array(rows)


def test_our_comp_file_reads_like_linuxcncs_sample():
    sample = _comp_file_rows((EXAMPLES / "linuxcnc_screwcompX.dat").read_text())
    tables = with_reversal(make_tables({"EXX": [0, 5, -3, 2, 0]}), "EXX", 1.5)
    ours = _comp_file_rows(compensate(make_machine(), tables, "linuxcnc").files["x.comp"])
    for rows in (sample, ours):
        # nominal ascending; forward and reverse actual positions within a hair of it
        assert np.all(np.diff(rows[:, 0]) > 0)
        assert np.abs(rows[:, 1:] - rows[:, [0]]).max() < 0.25
    # the sample's reverse column lies above the forward one (backlash-like), as ours
    # does for a table whose '-' pass reads more than the '+' pass
    assert np.all(sample[:, 2] >= sample[:, 1]) and np.all(ours[:, 2] >= ours[:, 1])


def _statements(text: str) -> list[tuple[str, tuple[str, ...], str]]:
    """(variable, indices, value) of every ``$NAME[i,...]=value`` line."""
    found = []
    for line in text.splitlines():
        match = re.fullmatch(r"\$(\w+)\[([^\]]*)\]=(.*)", line.strip())
        if match:
            found.append((match[1], tuple(match[2].split(",")), match[3]))
    return found


def test_our_eec_init_program_has_the_manuals_structure():
    manual = (EXAMPLES / "sinumerik_k3_eec_example.ini").read_text()
    machine = make_machine(axis_names={"X": "X1", "Y": "Y1", "Z": "Z1"})
    tables = make_tables({"EXX": [3, 10, 12, 5, 0]})
    ours = compensate(machine, tables, "sinumerik").files["AX_EEC.INI"]
    for text in (manual, ours):
        lines = [line for line in text.splitlines() if line.strip() and not line.startswith(";")]
        assert lines[0] == "%_N_AX_EEC_INI" and lines[1] == "CHANDATA(1)" and lines[-1] == "M17"
    manual_statements = _statements(manual)
    ours_x1 = [s for s in _statements(ours) if s[1][-1] == "X1"]
    assert {name for name, *_ in manual_statements} == {name for name, *_ in ours_x1}
    for statements in (manual_statements, ours_x1):
        values = {name: float(value) for name, indices, value in statements if len(indices) == 2}
        points = [int(idx[1]) for name, idx, _ in statements if name == "AA_ENC_COMP"]
        assert all(idx[0] == "0" for _, idx, _ in statements)  # compensation table 0
        assert all(re.fullmatch(NUMBER, value) for *_, value in statements)
        # the last point sits at MAX: MIN + STEP x (points - 1)
        span = values["AA_ENC_COMP_MAX"] - values["AA_ENC_COMP_MIN"]
        assert max(points) * values["AA_ENC_COMP_STEP"] == np.float64(span)
        assert values["AA_ENC_COMP_IS_MODULO"] == 0
