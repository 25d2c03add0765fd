"""Which samples of a tracker's stream lie on which measuring path of the program (seed 001).

A tracker logs on its own clock, not synchronised with the CNC. Everything here
uses the stream's geometry only, in the tracker's frame:

1. **Moves.** The machine ends every move of the program at rest (the program is
   straight moves, stop to stop). The path speed from the samples (central
   differences) drops to about zero at each junction: the stream splits there into
   moves, each with a displacement vector.
2. **The program's moves.** Measuring path 0, the move to path 1's start, path 1,
   ... The lengths of the moves and the angles between consecutive ones do not
   depend on the tracker's pose: the program's sequence is found in the stream's
   by them (the stream may hold more moves before and after).
3. **Rough pose.** The ends of the matched moves give pairs of points; the rigid
   fit (Kabsch) gives the tracker's pose.
4. **Cruise.** Of each measuring path only the samples at the path's cruise
   speed are kept: its acceleration and deceleration (and the servo lag's
   transients there) are dropped.
5. **Points aligned to the path, iteratively.** Each kept sample's foot on its
   path, the rigid fit between the samples and the feet, again until the pose
   settles; a sample farther from its path than :data:`OFF_PATH_MM` means the
   stream is not from this program.

Pure numpy; :class:`xmalign.errors.InputError` with the file and the line where
the stream cannot be used (a tracker that stood still, another program, a gap).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from xmalign.errors import InputError
from xmalign.formats.common import line_error
from xmalign.geometry import Vec
from xmalign.post.instruments import rigid_start

#: Below this path speed the SMR stands still, mm/s.
STOP_MM_S = 2.0
#: A sample interval this many times the stream's median is a gap.
GAP_FACTOR = 5.0
#: Moves shorter than this are not told apart from a stop, mm.
MIN_MOVE_MM = 0.5
#: The program's and the stream's moves agree within this length (mm + fraction) ...
LENGTH_TOLERANCE_MM = 1.0
LENGTH_TOLERANCE = 0.01
#: ... and this cosine of the angle between consecutive moves (moves longer than 20 mm).
ANGLE_TOLERANCE = 0.05
_ANGLE_MIN_MM = 20.0
#: Kept: the samples within this fraction of the path's cruise speed.
CRUISE_TOLERANCE = 0.03
#: A kept sample this far from its path (after the alignment) is on no path of the program.
OFF_PATH_MM = 1.0
#: Time over which the speed is taken (junctions), and smoothed (cruise), s.
_JUNCTION_S = 0.01
_CRUISE_S = 0.05
#: Junctions are the slowest sample within this time, s ...
_JUNCTION_WINDOW_S = 0.1
#: ... slower than this fraction of the fastest on either side within this time, s.
JUNCTION_RATIO = 0.7
_NEIGHBOURS_S = 0.5
_ALIGN_ITERATIONS = 30
_ALIGN_TOLERANCE_MM = 1e-4


@dataclass(frozen=True)
class StreamAssignment:
    """The samples of a stream on the program's measuring paths.

    ``sample``: indices into the stream (time order); ``path``: the program's path
    of each; ``rotation``, ``offset``: the tracker's pose found (``t = R p + c``,
    p the SMR in the MCS); ``off_path_um``: RMS distance of the kept samples from
    their paths after the alignment; ``dropped``: samples on no measuring path or in
    an acceleration, deceleration or stop.
    """

    sample: np.ndarray
    path: np.ndarray
    rotation: Vec
    offset: Vec
    off_path_um: float
    dropped: int


def program_moves(starts_mm: Vec, ends_mm: Vec) -> tuple[Vec, np.ndarray]:
    """The program's moves from path 0's start on: vectors (M, 3) and the path of each (-1: none).

    The move from one path's end to the next one's start is left out where it is
    shorter than :data:`MIN_MOVE_MM` (the machine goes straight on).
    """
    vectors, paths = [], []
    for number, (start, end) in enumerate(zip(starts_mm, ends_mm, strict=True)):
        if number and np.linalg.norm(start - ends_mm[number - 1]) >= MIN_MOVE_MM:
            vectors.append(start - ends_mm[number - 1])
            paths.append(-1)
        vectors.append(end - start)
        paths.append(number)
    return np.array(vectors), np.array(paths)


def _speed(time_s: Vec, points_mm: Vec, half: int) -> Vec:
    """Path speed by central differences over ``half`` samples each side, mm/s."""
    n = len(time_s)
    index = np.arange(n)
    low, high = np.maximum(index - half, 0), np.minimum(index + half, n - 1)
    span = np.maximum(time_s[high] - time_s[low], 1e-12)
    return np.linalg.norm(points_mm[high] - points_mm[low], axis=1) / span


def _check_clock(time_s: Vec, lines: np.ndarray, source: str) -> float:
    """The median sample interval; InputError where time goes back or stops (a gap)."""
    if len(time_s) < 3:
        raise InputError(f"{source}: {len(time_s)} samples are no stream")
    step = np.diff(time_s)
    if np.any(step <= 0):
        i = int(np.argmax(step <= 0)) + 1
        raise line_error(
            source, int(lines[i]), f"time_s {time_s[i]:g} does not go on from the row before"
        )
    interval = float(np.median(step))
    gap = step > GAP_FACTOR * interval
    if np.any(gap):
        i = int(np.argmax(gap)) + 1
        raise line_error(
            source,
            int(lines[i]),
            f"no sample for {step[i - 1]:.3f} s before time_s {time_s[i]:g} (the stream samples"
            f" every {interval:.4f} s): a gap, the tracker lost the SMR; measure the run again",
        )
    return interval


def stream_moves(time_s: Vec, tracker_mm: Vec, interval_s: float) -> list[tuple[int, int]]:
    """The stream's moves: (first, last) sample of each, in time order.

    Boundaries are the samples at rest (speed below :data:`STOP_MM_S`) and the
    junctions: the slowest sample within :data:`_JUNCTION_WINDOW_S` that is
    slower than :data:`JUNCTION_RATIO` of the fastest within :data:`_NEIGHBOURS_S`
    on each side (the machine stopped there and went on, faster than a sample
    interval shows at a low sample rate).
    """
    half = max(1, round(_JUNCTION_S / interval_s))
    speed = _speed(time_s, tracker_mm, half)
    slowest = speed <= _window(speed, max(1, round(_JUNCTION_WINDOW_S / interval_s)), np.min)
    reach = max(2, round(_NEIGHBOURS_S / interval_s))
    padded = np.pad(speed, reach, constant_values=0.0)
    views = np.lib.stride_tricks.sliding_window_view(padded, reach)
    before, after = views[: len(speed)].max(axis=1), views[reach + 1 :].max(axis=1)
    junction = slowest & (speed < JUNCTION_RATIO * np.minimum(before, after))
    boundary = (speed < STOP_MM_S) | junction
    edges = np.diff(np.concatenate([[1], boundary.astype(int), [1]]))
    firsts, lasts = np.flatnonzero(edges == -1), np.flatnonzero(edges == 1) - 1
    return [
        (int(a), int(b))
        for a, b in zip(firsts, lasts, strict=True)
        if np.linalg.norm(tracker_mm[b] - tracker_mm[a]) >= MIN_MOVE_MM
    ]


def _window(values: Vec, half: int, reduce: Callable[..., Vec]) -> Vec:
    """``reduce`` over each sample's window of ``half`` samples each side."""
    padded = np.pad(values, half, mode="edge")
    return reduce(np.lib.stride_tricks.sliding_window_view(padded, 2 * half + 1), axis=1)


def _turns(vectors: Vec) -> Vec:
    """Cosine of the angle between consecutive vectors (NaN where one is short), (M - 1,)."""
    length = np.linalg.norm(vectors, axis=1)
    unit = vectors / np.maximum(length, 1e-12)[:, None]
    cosine = np.sum(unit[1:] * unit[:-1], axis=1)
    short = (length[1:] < _ANGLE_MIN_MM) | (length[:-1] < _ANGLE_MIN_MM)
    return np.where(short, np.nan, cosine)


def match_moves(program_mm: Vec, stream_mm: Vec, slack_mm: Vec) -> int | None:
    """Where the program's moves start among the stream's (the best fit), None if nowhere.

    Compared by their lengths and the angles between consecutive moves (neither
    depends on the tracker's pose). ``slack_mm`` (per stream move): how much
    shorter its ends, the samples nearest the junctions, may make it.
    """
    m = len(program_mm)
    if len(stream_mm) < m:
        return None
    want, have = np.linalg.norm(program_mm, axis=1), np.linalg.norm(stream_mm, axis=1)
    want_turns, have_turns = _turns(program_mm), _turns(stream_mm)
    best, best_misfit = None, np.inf
    for k in range(len(stream_mm) - m + 1):
        lengths = np.abs(have[k : k + m] - want)
        if np.any(lengths > LENGTH_TOLERANCE_MM + LENGTH_TOLERANCE * want + slack_mm[k : k + m]):
            continue
        turns = np.abs(have_turns[k : k + m - 1] - want_turns)
        if np.any(turns[np.isfinite(turns)] > ANGLE_TOLERANCE):
            continue
        misfit = float(np.sum(lengths))
        if misfit < best_misfit:
            best, best_misfit = k, misfit
    return best


def _cruise(time_s: Vec, tracker_mm: Vec, first: int, last: int, interval_s: float) -> Vec:
    """The samples of a move at its cruise speed (indices into the stream)."""
    half = max(1, round(_CRUISE_S / interval_s))
    rows = np.arange(first, last + 1)
    low, high = np.maximum(rows - half, first), np.minimum(rows + half, last)
    speed = np.linalg.norm(tracker_mm[high] - tracker_mm[low], axis=1) / np.maximum(
        time_s[high] - time_s[low], 1e-12
    )
    n = len(rows)
    cruise = float(np.median(speed[n // 3 : max(n // 3 + 1, 2 * n // 3)]))
    keep = (np.abs(speed - cruise) <= CRUISE_TOLERANCE * cruise) & (rows - half >= first)
    return rows[keep & (rows + half <= last)]


def _feet(points_mm: Vec, starts_mm: Vec, ends_mm: Vec) -> Vec:
    """Each point's closest point on its segment (rows of ``starts_mm``/``ends_mm``)."""
    path = ends_mm - starts_mm
    length2 = np.maximum(np.sum(path**2, axis=1), 1e-12)
    fraction = np.clip(np.sum((points_mm - starts_mm) * path, axis=1) / length2, 0.0, 1.0)
    return starts_mm + fraction[:, None] * path


def assign_stream(
    time_s: Vec,
    tracker_mm: Vec,
    starts_mm: Vec,
    ends_mm: Vec,
    lines: np.ndarray,
    source: str,
) -> StreamAssignment:
    """The samples of one (station, run) of a stream on the program's measuring paths.

    Parameters
    ----------
    time_s : ndarray, shape (N,)
        The tracker's clock, increasing.
    tracker_mm : ndarray, shape (N, 3)
        SMR centre in the tracker's frame.
    starts_mm, ends_mm : ndarray, shape (P, 3)
        The program's measuring paths in order: the SMR's start and end in the MCS.
    lines : ndarray of int, shape (N,)
        Each sample's line in the file, for messages.
    source : str

    Raises
    ------
    InputError
        Time that goes back, a gap, an SMR that stood still, or moves that are not
        the program's (one line naming the file and, where there is one, the line).
    """
    interval = _check_clock(time_s, lines, source)
    moves = stream_moves(time_s, tracker_mm, interval)
    if not moves:
        raise InputError(
            f"{source}: the SMR stood still for the whole stream ({time_s[-1] - time_s[0]:.1f} s,"
            f" lines {lines[0]}-{lines[-1]}): the tracker did not see the program run"
        )
    vectors, paths = program_moves(starts_mm, ends_mm)
    seen = np.array([tracker_mm[b] - tracker_mm[a] for a, b in moves])
    speed = _speed(time_s, tracker_mm, 1)
    slack = np.array([(speed[a] + speed[b]) * interval for a, b in moves])
    k = match_moves(vectors, seen, slack)
    if k is None:
        raise InputError(
            f"{source}: the stream's {len(moves)} moves (lines {lines[0]}-{lines[-1]}) do not"
            f" hold the program's {len(vectors)} (its paths, and the moves between them, by"
            " length and angle): a stream of another program, or a run that was cut short"
        )
    matched = moves[k : k + len(vectors)]
    program_ends = np.cumsum(np.vstack([starts_mm[:1], vectors]), axis=0)
    pairs_mcs = np.vstack([program_ends[:-1], program_ends[1:]])
    pairs_tracker = np.vstack(
        [tracker_mm[[a for a, _ in matched]], tracker_mm[[b for _, b in matched]]]
    )
    rotation, offset = rigid_start(pairs_mcs, pairs_tracker)
    kept = [
        (_cruise(time_s, tracker_mm, a, b, interval), number)
        for (a, b), number in zip(matched, paths, strict=True)
        if number >= 0
    ]
    sample = np.concatenate([rows for rows, _ in kept])
    path = np.concatenate([np.full(len(rows), number) for rows, number in kept])
    if len(sample) < 3:
        raise InputError(
            f"{source}: no sample at a path's cruise speed (lines {lines[0]}-{lines[-1]}):"
            " the tracker samples too slowly for these paths"
        )
    rotation, offset, off_path = _align(
        tracker_mm[sample], starts_mm[path], ends_mm[path], rotation, offset
    )
    worst = int(np.argmax(off_path))
    if off_path[worst] > OFF_PATH_MM:
        raise line_error(
            source,
            int(lines[sample[worst]]),
            f"the sample lies {off_path[worst]:.2f} mm off path {path[worst]} of the program"
            f" (more than {OFF_PATH_MM:g} mm): a stream of another program, or the tracker moved",
        )
    return StreamAssignment(
        sample=sample,
        path=path,
        rotation=rotation,
        offset=offset,
        off_path_um=float(np.sqrt(np.mean(off_path**2)) * 1e3),
        dropped=len(time_s) - len(sample),
    )


def _align(
    tracker_mm: Vec, starts_mm: Vec, ends_mm: Vec, rotation: Vec, offset: Vec
) -> tuple[Vec, Vec, Vec]:
    """Seed 001's fine alignment: feet on the paths, rigid fit to them, until the pose settles.

    Returns the pose and each sample's distance from its path, mm.
    """
    for _ in range(_ALIGN_ITERATIONS):
        mcs = (tracker_mm - offset) @ rotation
        feet = _feet(mcs, starts_mm, ends_mm)
        new_rotation, new_offset = rigid_start(feet, tracker_mm)
        moved = np.max(
            np.linalg.norm(
                (feet @ new_rotation.T + new_offset) - (feet @ rotation.T + offset), axis=1
            )
        )
        rotation, offset = new_rotation, new_offset
        if moved < _ALIGN_TOLERANCE_MM:
            break
    mcs = (tracker_mm - offset) @ rotation
    return rotation, offset, np.linalg.norm(mcs - _feet(mcs, starts_mm, ends_mm), axis=1)
