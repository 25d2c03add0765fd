"""Tally the bad-input table of tests/xmalign/bad_input_cases.py (issue 11's closing table).

    PYTHONPATH=$PWD python tests/benchmarks/bench_bad_input.py [--lines]

Prints: cases tried, clean errors, tracebacks, wrongly accepted, unclear
(several lines or the file not named), files damaged; ``--lines`` also prints
every case's stderr line.
"""

from __future__ import annotations

import sys
import tempfile
from collections import Counter
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "xmalign"))

from bad_input_cases import CASES, run_case, verdict  # noqa: E402


def main() -> None:
    tally: Counter[str] = Counter()
    damaged = 0
    for case in CASES:
        with tempfile.TemporaryDirectory() as folder, pytest.MonkeyPatch.context() as patch:
            outcome = run_case(case, Path(folder), patch)
        result = verdict(case, outcome)
        tally[result] += 1
        damaged += bool(outcome.damaged or outcome.leftovers)
        if "--lines" in sys.argv or result != "clean":
            shown = outcome.stderr_lines or [outcome.traceback.strip().splitlines()[-1:]]
            print(f"{result:9} {case.id:40} {shown}")
    print(
        "| cases tried | clean errors | tracebacks | wrongly accepted | unclear | files damaged |"
    )
    print("|---|---|---|---|---|---|")
    print(
        f"| {len(CASES)} | {tally['clean']} | {tally['traceback']} | {tally['accepted']}"
        f" | {tally['unclear']} | {damaged} |"
    )


if __name__ == "__main__":
    main()
