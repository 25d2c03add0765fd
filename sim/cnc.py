"""Simulated CNC: executes the G-code xmalign writes and moves a virtual machine.

Implements the :class:`~xmalign.roles.MachineMover` role on a
:class:`~xmalign.roles.Clock`. Motion is analytic in time (straight-line
interpolation with a trapezoidal velocity profile: programmed feed, constant
acceleration), evaluated at ``clock.now()``; nothing is ticked, so hours of
machine time take milliseconds on a virtual clock.

:meth:`SimulatedCnc.run_program` reads a whole program first, as a control's
block preparation would, and refuses what a real control would refuse (unknown
word or block, inch units, missing or zero feed, a move outside the travel,
missing program end) with an :class:`~xmalign.errors.InputError` naming the
line; only then does it execute, yielding a :class:`CncEvent` at every
operator message, programmed stop and dwell (the dwell time runs after the
consumer resumes the generator, counted from the dwell's start).

Coordinates are CNC (machine) coordinates of the tool point (mm); the
machine's geometric errors are not applied here. Programs may move in machine
coordinates (``G53``, ``SUPA``, ``M91``) or in a work offset they set
themselves (``G10 L2``, ``$P_UIFR[n]=CTRANS(..)``, then ``G54`` .. ``G59``);
all work offsets start at zero, as if the machine's were cleared.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike

from xmalign.errors import InputError, OutOfRangeError
from xmalign.geometry import Vec
from xmalign.machine import AXES, Machine
from xmalign.roles import Clock

DIALECTS = ("iso", "sinumerik", "heidenhain", "linuxcnc")
#: Default path acceleration, mm/s².
DEFAULT_ACCELERATION_MM_S2 = 1000.0


# ---------------------------------------------------------------- motion


@dataclass(frozen=True)
class _Segment:
    """A straight move started at ``t0_s`` with a trapezoidal velocity profile."""

    start_mm: Vec
    end_mm: Vec
    t0_s: float
    speed_mm_s: float
    accel_mm_s2: float

    @property
    def length_mm(self) -> float:
        return float(np.linalg.norm(self.end_mm - self.start_mm))

    @property
    def _peak_mm_s(self) -> float:
        return min(self.speed_mm_s, math.sqrt(self.length_mm * self.accel_mm_s2))

    @property
    def duration_s(self) -> float:
        if self.length_mm == 0.0:
            return 0.0
        peak = self._peak_mm_s
        ramp_s = peak / self.accel_mm_s2
        cruise_mm = self.length_mm - peak * ramp_s
        return 2.0 * ramp_s + cruise_mm / peak

    def distance_mm(self, t_s: float) -> float:
        """Path length covered at time ``t_s``."""
        length, t, total = self.length_mm, t_s - self.t0_s, self.duration_s
        if t <= 0.0 or length == 0.0:
            return 0.0
        if t >= total:
            return length
        a, peak = self.accel_mm_s2, self._peak_mm_s
        ramp_s = peak / a
        if t < ramp_s:
            return 0.5 * a * t * t
        left = total - t
        if left < ramp_s:
            return length - 0.5 * a * left * left
        return 0.5 * peak * ramp_s + peak * (t - ramp_s)

    def velocity_mm_s(self, t_s: float) -> float:
        """Path speed at time ``t_s``, mm/s."""
        t, total = t_s - self.t0_s, self.duration_s
        if t <= 0.0 or t >= total:
            return 0.0
        a, peak = self.accel_mm_s2, self._peak_mm_s
        return min(a * t, a * (total - t), peak)

    def position_mm(self, t_s: float) -> Vec:
        if self.length_mm == 0.0:
            return self.end_mm.copy()
        fraction = self.distance_mm(t_s) / self.length_mm
        return self.start_mm + fraction * (self.end_mm - self.start_mm)


# ---------------------------------------------------------------- program steps


@dataclass(frozen=True)
class _Move:
    line_no: int
    target_mm: Vec
    feed_mm_min: float


@dataclass(frozen=True)
class _Dwell:
    line_no: int
    seconds: float
    comment: str


@dataclass(frozen=True)
class _Stop:
    line_no: int


@dataclass(frozen=True)
class _Message:
    line_no: int
    text: str


@dataclass(frozen=True)
class _End:
    line_no: int


_Step = _Move | _Dwell | _Stop | _Message | _End


@dataclass(frozen=True)
class CncEvent:
    """What the program reached while it runs.

    ``kind`` is ``message`` (``text`` the message), ``stop`` (programmed stop;
    ``text`` the last message), ``dwell`` (``text`` the last comment, which
    names the target in xmalign's programs; ``dwell_s`` its length) or ``end``.
    ``position_mm`` (3,) is the CNC tool point, ``time_s`` the clock time.
    """

    kind: Literal["message", "stop", "dwell", "end"]
    line_no: int
    time_s: float
    position_mm: Vec
    text: str = ""
    dwell_s: float = 0.0


class _Reader:
    """Modal state shared by the dialect readers: position, motion mode, feed, travel."""

    def __init__(self, machine: Machine, position_mm: Vec, rapid_mm_min: float) -> None:
        self.machine = machine
        self.position = np.array(position_mm, dtype=float)
        self.rapid_mm_min = rapid_mm_min
        self.motion: int | None = None
        self.feed: float | None = None
        self.comment = ""
        self.steps: list[_Step] = []
        self.ended = False
        self.work_offsets = {n: np.zeros(3) for n in range(1, 7)}
        self.active_offset = 1

    def fail(self, line_no: int, reason: str) -> InputError:
        return InputError(f"program line {line_no}: {reason}")

    def set_feed(self, line_no: int, value: float) -> None:
        if not value > 0.0:
            raise self.fail(line_no, f"feed F{value:g} must be greater than zero")
        self.feed = value

    def move(
        self, line_no: int, axes: dict[str, float], rapid: bool, machine: bool = False
    ) -> None:
        """Move to ``axes`` (program coordinates, or machine coordinates with ``machine``)."""
        target = self.position.copy()
        offset = np.zeros(3) if machine else self.work_offsets[self.active_offset]
        for axis, value in axes.items():
            target[AXES.index(axis)] = value + offset[AXES.index(axis)]
        if not self.machine.within_travel(target):
            raise self.fail(
                line_no,
                f"move to [{', '.join(f'{v:.3f}' for v in target)}] mm leaves the travel"
                f" {[self.machine.travel_mm[a] for a in AXES]}",
            )
        if rapid:
            feed = self.rapid_mm_min
        elif self.feed is None:
            raise self.fail(line_no, "feed move without a programmed feed (F missing)")
        else:
            feed = self.feed
        self.steps.append(_Move(line_no, target, feed))
        self.position = target

    def dwell(self, line_no: int, seconds: float) -> None:
        if not (math.isfinite(seconds) and seconds >= 0.0):
            raise self.fail(line_no, f"dwell time {seconds:g} s must be >= 0")
        self.steps.append(_Dwell(line_no, seconds, self.comment))

    def end(self, line_no: int) -> None:
        self.steps.append(_End(line_no))
        self.ended = True


# ---------------------------------------------------------------- word-address dialects

_WORD = re.compile(r"\s*([A-Z])\s*([-+]?(?:\d+\.?\d*|\.\d+))")
_METRIC = {"iso": {21}, "linuxcnc": {21}, "sinumerik": {71, 710}}
_INCH = {"iso": {20}, "linuxcnc": {20}, "sinumerik": {70, 700}}
_MODAL_NOOPS = {17, 40, 49, 80, 90, 94}
#: Work offset selection: G54 .. G59 -> 1 .. 6.
_WORK_OFFSETS = {54: 1, 55: 2, 56: 3, 57: 4, 58: 5, 59: 6}
#: G-codes with a decimal point that only suspend offsets the simulator has not got.
_DECIMAL_NOOPS = {"linuxcnc": {"92.2"}}
#: Words that give the dwell time: Fanuc P ms or X s, LinuxCNC P s, Sinumerik F s.
_DWELL_WORDS = {"iso": ("P", "X"), "linuxcnc": ("P",), "sinumerik": ("F",)}


def _split_words(line_no: int, code: str, reader: _Reader) -> list[tuple[str, str]]:
    words, position = [], 0
    code = code.upper().rstrip()
    while position < len(code):
        match = _WORD.match(code, position)
        if match is None:
            raise reader.fail(line_no, f"cannot read '{code[position:].strip()}'")
        words.append((match.group(1), match.group(2)))
        position = match.end()
    return words


def _g_number(line_no: int, value: str, reader: _Reader) -> int:
    if "." in value:
        raise reader.fail(line_no, f"unsupported G{value}")
    return int(value)


def _dwell_seconds(dialect: str, line_no: int, words: dict[str, str], reader: _Reader) -> float:
    allowed = _DWELL_WORDS[dialect]
    given = [letter for letter in words if letter in allowed]
    if len(given) != 1:
        raise reader.fail(line_no, f"dwell needs exactly one of {', '.join(allowed)}")
    value = words[given[0]]
    if dialect == "iso" and given[0] == "P":
        if "." in value:
            raise reader.fail(line_no, "G04 P takes whole milliseconds (no decimal point)")
        return int(value) / 1000.0
    return float(value)


def _set_work_offset(line_no: int, words: dict[str, str], reader: _Reader) -> None:
    """``G10 L2 P<n> X.. Y.. Z.. [R0]``: the origin of work offset n in machine mm."""
    if words.get("L") != "2" or "P" not in words or int(float(words["P"])) not in range(1, 7):
        raise reader.fail(line_no, "G10 needs L2 and P1 .. P6 (work offset origin)")
    if float(words.get("R", "0")) != 0.0 or set(words) - {"L", "P", "R", "X", "Y", "Z"}:
        raise reader.fail(line_no, "G10 L2 takes X, Y, Z (and R0) only")
    offset = reader.work_offsets[int(float(words["P"]))]
    for axis in AXES:
        if axis in words:
            offset[AXES.index(axis)] = float(words[axis])


def _word_block(
    dialect: str, line_no: int, code: str, reader: _Reader, machine: bool = False
) -> None:
    pairs = _split_words(line_no, code, reader)
    noops = _DECIMAL_NOOPS.get(dialect, set())
    pairs = [(letter, v) for letter, v in pairs if not (letter == "G" and v in noops)]
    if not pairs:
        return
    g_codes = [_g_number(line_no, v, reader) for letter, v in pairs if letter == "G"]
    m_codes = [int(float(v)) for letter, v in pairs if letter == "M"]
    words: dict[str, str] = {}
    for letter, value in pairs:
        if letter in "GMN":
            continue
        if letter in words:
            raise reader.fail(line_no, f"word {letter} given twice")
        words[letter] = value
    for g in g_codes:
        if g in _INCH[dialect]:
            raise reader.fail(line_no, f"G{g}: inch units are not supported, program in mm")
        known = {0, 1, 4, 10, 52, 53} | _METRIC[dialect] | _MODAL_NOOPS | set(_WORK_OFFSETS)
        if g not in known or (dialect == "sinumerik" and g in (10, 52, 53)):
            raise reader.fail(line_no, f"unsupported G{g}")
        if g in _WORK_OFFSETS:
            reader.active_offset = _WORK_OFFSETS[g]
    machine = machine or 53 in g_codes
    if 10 in g_codes:
        _set_work_offset(line_no, words, reader)
    elif 52 in g_codes:
        if any(float(words.get(axis, "0")) != 0.0 for axis in AXES) or set(words) - set(AXES):
            raise reader.fail(
                line_no, "G52 local coordinate systems are not supported (only X0 Y0 Z0)"
            )
    elif 4 in g_codes:
        seconds = _dwell_seconds(dialect, line_no, words, reader)
        extra = set(words) - set(_DWELL_WORDS[dialect])
        if extra or {0, 1} & set(g_codes):
            raise reader.fail(line_no, "a dwell must stand alone in its block")
        reader.dwell(line_no, seconds)
    else:
        if dialect == "sinumerik" and words.get("D") == "0":
            del words["D"]  # D0: tool offset off
        unknown = set(words) - {"X", "Y", "Z", "F"}
        if unknown:
            raise reader.fail(line_no, f"unknown word {sorted(unknown)[0]}")
        for g in g_codes:
            if g in (0, 1):
                reader.motion = g
        if "F" in words:
            reader.set_feed(line_no, float(words["F"]))
        axes: dict[str, float] = {a: float(words[a]) for a in AXES if a in words}
        if axes:
            if reader.motion is None:
                raise reader.fail(line_no, "axis words without G0 or G1")
            reader.move(line_no, axes, rapid=reader.motion == 0, machine=machine)
    for m in m_codes:
        if m in (2, 30):
            reader.end(line_no)
        elif m in (0, 1):
            reader.steps.append(_Stop(line_no))
        else:
            raise reader.fail(line_no, f"unsupported M{m}")


_PAREN = re.compile(r"\(([^()]*)\)")
_SINUMERIK_MSG = re.compile(r'MSG\s*\(\s*(?:"([^"]*)")?\s*\)', re.IGNORECASE)
_SINUMERIK_SUPA = re.compile(r"\bSUPA\b", re.IGNORECASE)
_SINUMERIK_FRAME = re.compile(
    r"\s*\$P_UIFR\[([1-6])\]\s*=\s*CTRANS\(\s*X\s*,\s*([-+.\d]+)\s*,\s*Y\s*,\s*([-+.\d]+)"
    r"\s*,\s*Z\s*,\s*([-+.\d]+)\s*\)\s*",
    re.IGNORECASE,
)


def _read_parenthesised(dialect: str, line_no: int, text: str, reader: _Reader) -> str:
    """Remove ``(comments)`` (and LinuxCNC ``(MSG,..)``), record them, return the code."""
    for match in _PAREN.finditer(text):
        body = match.group(1)
        if dialect == "linuxcnc" and body.upper().startswith("MSG,"):
            reader.steps.append(_Message(line_no, body[4:].strip()))
        else:
            reader.comment = body.strip()
    code = _PAREN.sub(" ", text)
    if "(" in code or ")" in code:
        raise reader.fail(line_no, "unbalanced parenthesis in comment")
    return code


def _read_word_program(dialect: str, lines: list[str], reader: _Reader) -> None:
    for line_no, raw in enumerate(lines, start=1):
        text = raw.strip()
        if reader.ended or not text or (dialect in ("iso", "linuxcnc") and text == "%"):
            continue
        if dialect == "sinumerik":
            code, _, comment = text.partition(";")
            if comment:
                reader.comment = comment.strip()
            message = _SINUMERIK_MSG.search(code)
            if message:
                if message.group(1):
                    reader.steps.append(_Message(line_no, message.group(1)))
                code = _SINUMERIK_MSG.sub(" ", code)
            frame = _SINUMERIK_FRAME.fullmatch(code)
            if frame:
                origin = [float(v) for v in frame.groups()[1:]]
                reader.work_offsets[int(frame.group(1))] = np.array(origin)
                continue
            machine = bool(_SINUMERIK_SUPA.search(code))
            code = _SINUMERIK_SUPA.sub(" ", code)
        else:
            machine = False
            code = _read_parenthesised(dialect, line_no, text, reader)
            if dialect == "linuxcnc":
                code, _, comment = code.partition(";")
                if comment:
                    reader.comment = comment.strip()
            if dialect == "iso" and re.fullmatch(r"\s*O\d+\s*", code) and not reader.steps:
                continue
        _word_block(dialect, line_no, code, reader, machine)


# ---------------------------------------------------------------- Heidenhain conversational

_HH_BLOCK = re.compile(r"\s*(\d+)\s+(.*?)\s*$")
_HH_PGM = re.compile(r"(BEGIN|END) PGM (\S+) (MM|INCH)")
_HH_AXIS = re.compile(r"([XYZ])([-+]\d+\.?\d*|[-+]\.\d+)")


def _heidenhain_l_block(line_no: int, tokens: list[str], reader: _Reader) -> None:
    axes: dict[str, float] = {}
    rapid = False
    for token in tokens:
        axis = _HH_AXIS.fullmatch(token)
        if axis:
            axes[axis.group(1)] = float(axis.group(2))
        elif token == "R0":
            continue
        elif token == "FMAX":
            rapid = True
        elif re.fullmatch(r"F\d+\.?\d*", token):
            reader.set_feed(line_no, float(token[1:]))
        elif re.fullmatch(r"M\d+", token):
            continue
        else:
            raise reader.fail(line_no, f"unknown word '{token}' in L block")
    if axes:
        reader.move(line_no, axes, rapid=rapid, machine="M91" in tokens)
    _heidenhain_m(line_no, [t for t in tokens if re.fullmatch(r"M\d+", t)], reader)


def _heidenhain_m(line_no: int, tokens: list[str], reader: _Reader) -> None:
    for token in tokens:
        m = int(token[1:])
        if m in (2, 30):
            reader.steps.append(_End(line_no))
        elif m in (0, 1):
            reader.steps.append(_Stop(line_no))
        elif m != 91:  # M91: coordinates refer to the machine datum (those of the simulator)
            raise reader.fail(line_no, f"unsupported {token}")


def _read_heidenhain(lines: list[str], reader: _Reader) -> None:
    name = None
    dwell_defined = False
    for line_no, raw in enumerate(lines, start=1):
        if not raw.strip():
            continue
        block = _HH_BLOCK.fullmatch(raw)
        if block is None:
            raise reader.fail(line_no, "a block must start with its block number")
        content = block.group(2)
        pgm = _HH_PGM.fullmatch(content)
        if name is None:
            if not (pgm and pgm.group(1) == "BEGIN"):
                raise reader.fail(line_no, "program must start with BEGIN PGM <name> MM")
            if pgm.group(3) == "INCH":
                raise reader.fail(line_no, "inch programs are not supported, program in MM")
            name = pgm.group(2)
        elif pgm and pgm.group(1) == "END":
            if pgm.group(2) != name:
                raise reader.fail(line_no, f"END PGM {pgm.group(2)} does not match {name}")
            reader.end(line_no)
            return
        elif content.startswith(";") or content.startswith("*"):
            reader.comment = content.lstrip(";*").strip()
        elif content == "CYCL DEF 9.0 DWELL TIME":
            dwell_defined = True
        elif content.startswith("CYCL DEF 9.1"):
            dwell = re.fullmatch(r"CYCL DEF 9\.1\s+DWELL\s+(\d+\.?\d*)", content)
            if not (dwell and dwell_defined):
                raise reader.fail(line_no, "expected CYCL DEF 9.0 DWELL TIME, then 9.1 DWELL <s>")
            reader.dwell(line_no, float(dwell.group(1)))
            dwell_defined = False
        elif content == "TOOL CALL 0 Z":
            continue  # tool of length 0: no tool length compensation
        elif content == "STOP" or content.startswith("STOP "):
            reader.steps.append(_Stop(line_no))
            _heidenhain_m(line_no, content.split()[1:], reader)
        elif content == "L" or content.startswith("L "):
            _heidenhain_l_block(line_no, content.split()[1:], reader)
        else:
            raise reader.fail(line_no, f"unknown block '{content}'")


def read_program(
    text: str, dialect: str, machine: Machine, position_mm: ArrayLike, rapid_mm_min: float
) -> list[_Step]:
    """Check a whole program and turn it into steps; raises InputError naming the line."""
    if dialect not in DIALECTS:
        raise InputError(f"unknown G-code dialect '{dialect}' (known: {', '.join(DIALECTS)})")
    reader = _Reader(machine, np.asarray(position_mm, dtype=float), rapid_mm_min)
    lines = text.splitlines()
    if dialect == "heidenhain":
        _read_heidenhain(lines, reader)
    else:
        _read_word_program(dialect, lines, reader)
    if not reader.ended:
        end = "END PGM" if dialect == "heidenhain" else "M30 or M2"
        raise InputError(f"program line {len(lines)}: program end ({end}) missing")
    return reader.steps


# ---------------------------------------------------------------- the CNC


class SimulatedCnc:
    """A 3-axis CNC on a clock: the ``MachineMover`` role plus program execution.

    Parameters
    ----------
    machine : Machine
        Travel limits and rapid feed.
    clock : Clock
        Time source; ``sleep`` is how the CNC lets time pass.
    position_mm : array_like, shape (3,), optional
        Start position; default the top of Z at the X and Y minimum.
    acceleration_mm_s2 : float, optional
        Path acceleration and deceleration; default the machine file's
        ``cnc.acceleration_mm_s2``, else ``DEFAULT_ACCELERATION_MM_S2``.
    """

    def __init__(
        self,
        machine: Machine,
        clock: Clock,
        position_mm: ArrayLike | None = None,
        acceleration_mm_s2: float | None = None,
    ) -> None:
        if acceleration_mm_s2 is None:
            acceleration_mm_s2 = machine.cnc.acceleration_mm_s2 or DEFAULT_ACCELERATION_MM_S2
        if not acceleration_mm_s2 > 0:
            raise InputError(f"acceleration {acceleration_mm_s2} mm/s^2 must be > 0")
        self._machine = machine
        self._clock = clock
        self._acceleration = acceleration_mm_s2
        start = (
            np.array([machine.travel_min_mm[0], machine.travel_min_mm[1], machine.travel_max_mm[2]])
            if position_mm is None
            else np.asarray(position_mm, dtype=float)
        )
        self._check_travel(start)
        self._segment = _Segment(start, start, clock.now(), 1.0, acceleration_mm_s2)

    def _check_travel(self, position_mm: Vec) -> None:
        if not self._machine.within_travel(position_mm):
            raise OutOfRangeError(
                f"[{', '.join(f'{v:.3f}' for v in position_mm)}] mm is outside the travel of"
                f" '{self._machine.name}'"
            )

    def position_mm(self) -> Vec:
        """Commanded-path tool point at the clock's present time, shape (3,)."""
        return self._segment.position_mm(self._clock.now())

    def is_standstill(self) -> bool:
        return self._clock.now() >= self._segment.t0_s + self._segment.duration_s

    def speed_mm_s(self) -> float:
        """Path speed of the tool point at the clock's present time, mm/s."""
        return self._segment.velocity_mm_s(self._clock.now())

    def start_move(self, position_mm: ArrayLike, feed_mm_min: float) -> float:
        """Start a straight move from the present position; returns its duration, s.

        The feed is limited to the rapid feed. Raises OutOfRangeError for a target
        outside the travel, InputError for a feed that is not > 0.
        """
        target = np.asarray(position_mm, dtype=float)
        self._check_travel(target)
        if not (math.isfinite(feed_mm_min) and feed_mm_min > 0):
            raise InputError(f"feed {feed_mm_min} mm/min must be > 0")
        speed = min(feed_mm_min, self._machine.feed_mm_min.rapid) / 60.0
        now = self._clock.now()
        self._segment = _Segment(self.position_mm(), target, now, speed, self._acceleration)
        return self._segment.duration_s

    def stop(self) -> None:
        """Stop where the tool point is now, at once (a feed hold of the simulated CNC)."""
        now = self._clock.now()
        here = self._segment.position_mm(now)
        self._segment = _Segment(here, here, now, 1.0, self._acceleration)

    def move_to(self, position_mm: Vec, feed_mm_min: float) -> None:
        """Move the tool point and return when it stands still there."""
        self._clock.sleep(self.start_move(position_mm, feed_mm_min))

    def run_program(self, text: str, dialect: str) -> Iterator[CncEvent]:
        """Check, then execute a program; yields at messages, stops, dwells and the end."""
        steps = read_program(
            text, dialect, self._machine, self.position_mm(), self._machine.feed_mm_min.rapid
        )
        last_message = ""
        for step in steps:
            if isinstance(step, _Move):
                self.move_to(step.target_mm, step.feed_mm_min)
                continue
            if isinstance(step, _Message):
                last_message = step.text
                yield self._event("message", step.line_no, step.text)
            elif isinstance(step, _Stop):
                yield self._event("stop", step.line_no, last_message)
            elif isinstance(step, _Dwell):
                started = self._clock.now()
                yield self._event("dwell", step.line_no, step.comment, step.seconds)
                self._clock.sleep(started + step.seconds - self._clock.now())
            else:
                yield self._event("end", step.line_no)
                return

    def _event(
        self,
        kind: Literal["message", "stop", "dwell", "end"],
        line_no: int,
        text: str = "",
        dwell_s: float = 0.0,
    ) -> CncEvent:
        return CncEvent(kind, line_no, self._clock.now(), self.position_mm(), text, dwell_s)


def run_to_end(events: Iterator[CncEvent], on_event: Callable[[CncEvent], None]) -> None:
    """Drive a running program to its end, calling ``on_event`` at every event."""
    for event in events:
        on_event(event)
