"""Recognise ``-`` passes whose linear datum was re-zeroed (docs/conventions.md, linear channel).

The interferometer counts on through both passes of a run, so at the target
where the ``-`` pass starts (the ``+`` pass's last) both passes read about the
same linear value; they differ only by the reversal there. A ``-`` pass that
was zeroed again when it started reads there what the ``+`` pass read at its
own datum instead, and ``post`` would take the jump for a reversal of the same
size (and a large sigma0).
"""

from __future__ import annotations

import numpy as np

from xmalign.post.lines import UM_PER_MM, LineData

#: A ``+`` pass that moves its linear reading by less than this over the line cannot
#: tell a re-zeroed ``-`` pass from a continued one, um.
MIN_TRAVEL_READING_UM = 5.0
#: The ``-`` pass's first reading must be this many times closer to the ``+`` pass's
#: datum than to the ``+`` pass's reading at the same target.
CLOSER_FACTOR = 4.0


def rezeroed_runs(data: LineData) -> list[tuple[int, float, float]]:
    """Runs of a line whose ``-`` pass looks re-zeroed.

    Returns
    -------
    list of (run, plus_um, minus_um)
        The run, and the ``+`` and ``-`` linear readings (um) at the target
        where the ``-`` pass starts.
    """
    found = []
    linear_um = data.channels[:, 0] * UM_PER_MM
    for run in np.unique(data.run):
        plus = (data.run == run) & (data.sign > 0)
        minus = (data.run == run) & (data.sign < 0)
        if not plus.any() or not minus.any():
            continue
        plus_index, plus_um = data.index[plus], linear_um[plus]
        datum_um = plus_um[np.argmin(plus_index)]
        turn = int(plus_index.max())
        at_turn = minus & (data.index == turn)
        if not at_turn.any():
            continue
        plus_turn_um = float(plus_um[np.argmax(plus_index)])
        minus_turn_um = float(linear_um[at_turn][0])
        moved = abs(plus_turn_um - datum_um)
        to_datum = abs(minus_turn_um - datum_um)
        to_plus = abs(minus_turn_um - plus_turn_um)
        if moved >= MIN_TRAVEL_READING_UM and CLOSER_FACTOR * to_datum < to_plus:
            found.append((int(run), plus_turn_um, minus_turn_um))
    return found


def datum_warnings(lines: list[LineData]) -> list[str]:
    """One sentence per line with re-zeroed ``-`` passes, saying what it means."""
    warnings = []
    for data in lines:
        runs = rezeroed_runs(data)
        if not runs:
            continue
        run, plus_um, minus_um = runs[0]
        listed = ", ".join(str(r) for r, _, _ in runs)
        warnings.append(
            f"line {data.label} run {listed}: the '-' pass reads {minus_um:.1f} um where it"
            f" starts, the '+' pass {plus_um:.1f} um at the same target (run {run}): its linear"
            " datum looks re-zeroed at the turn, but the interferometer must count on through"
            " both passes of a run (docs/conventions-notes.md, linear datum); the reversal"
            " tables and sigma0 of this fit are wrong. Re-measure without zeroing between the"
            " passes"
        )
    return warnings
