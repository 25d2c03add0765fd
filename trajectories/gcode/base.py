"""The interface every G-code dialect implements.

A dialect turns abstract steps (move, dwell, comment, message, stop) into the
blocks of its controller. Coordinates given to it are absolute metric machine
coordinates of the CNC tool point (mm), feeds mm/min, dwell times s.

Every dialect cancels tool length and radius compensation at the start and
moves in machine coordinates: with the controller's machine-coordinate word
(G53, SUPA, M91) on every block, or, where that cannot feed (Fanuc's G53 is
rapid only) or where the machine file asks for it (``cnc.work_offset``), in a
work offset the program sets itself, converting machine to program
coordinates. Retracts are always in machine coordinates (docs/controllers.md).
"""

from __future__ import annotations

import re
from abc import ABC, abstractmethod
from collections.abc import Iterable, Mapping
from pathlib import PurePath

from xmalign.formats.provenance import FileSource, history_lines
from xmalign.machine import AXES, WorkOffset

#: Characters a comment or message may keep; the rest (parentheses, quotes) end comments.
_UNSAFE = re.compile(r"[^A-Za-z0-9 .,:;+\-=/_%#*]")


#: The longest file name a history comment names in full (a block has a length limit).
MAX_NAME_CHARS = 80


def plain_text(text: str) -> str:
    """``text`` without characters that would end a comment or message early."""
    return _UNSAFE.sub("", text)


def _short(source: FileSource) -> FileSource:
    """The source named by its file name only (the program lies beside it), cut short."""
    name = PurePath(source.path).name
    if len(name) > MAX_NAME_CHARS:
        name = name[:MAX_NAME_CHARS] + "..."
    return FileSource(source.role, name, source.sha256)


class Dialect(ABC):
    """Spelling of one controller's G-code; each method returns whole blocks."""

    #: Dialect name as used by ``--dialect``.
    name: str = ""

    def __init__(
        self,
        program_name: str = "XMALIGN",
        work_offset: WorkOffset | None = None,
        stop_at_points: bool = False,
    ) -> None:
        self.program_name = program_name
        self.work_offset = work_offset
        #: A programmed stop at each capture point instead of the dwell: for a controller
        #: that xmalign itself resumes once the point is captured (docs/hardware.md).
        self.stop_at_points = stop_at_points

    def capture_wait(self, seconds: float) -> list[str]:
        """What the program does at a capture point: dwell, or stop for xmalign."""
        return [self.stop()] if self.stop_at_points else self.dwell(seconds)

    def program_axes(self, axes_mm: Mapping[str, float]) -> dict[str, float]:
        """Machine coordinates of the named axes in program coordinates (work offset removed)."""
        if self.work_offset is None:
            return dict(axes_mm)
        origin: dict[str, float] = dict(zip(AXES, self.work_offset.origin_mm, strict=True))
        return {axis: value - origin[axis] for axis, value in axes_mm.items()}

    def offset_words(self) -> str:
        """``X.. Y.. Z..`` of the work offset's origin (machine mm)."""
        assert self.work_offset is not None
        return words(dict(zip(AXES, self.work_offset.origin_mm, strict=True)))

    @abstractmethod
    def begin(self) -> list[str]:
        """Program start: name, metric, absolute, feed per minute."""

    @abstractmethod
    def end(self, retract_mm: Mapping[str, float]) -> list[str]:
        """Rapid retract to ``retract_mm`` (machine coordinates) and program end."""

    @abstractmethod
    def retract(self, axes_mm: Mapping[str, float]) -> str:
        """Rapid move of the named axes in machine coordinates, whatever the work offset."""

    @abstractmethod
    def comment(self, text: str) -> str: ...

    def history(self, format_name: str, inputs: Iterable[FileSource] = ()) -> list[str]:
        """The program's history as comment blocks: format, software, time, the dialect and
        each input's ``input ROLE: SHA-256  FILE NAME`` (docs/formats.md)."""
        lines = history_lines(format_name, map(_short, inputs), {"dialect": self.name})
        return [self.comment(line) for line in lines]

    @abstractmethod
    def message(self, text: str) -> str:
        """A message the controller shows to the operator (a comment where it has none)."""

    def stop(self) -> str:
        """Programmed stop; the operator continues with cycle start."""
        return "M0"

    @abstractmethod
    def rapid(self, axes_mm: Mapping[str, float]) -> str:
        """Rapid move of the named axes (``{"X": .., "Z": ..}``, machine coordinates)."""

    @abstractmethod
    def feed(self, axes_mm: Mapping[str, float], feed_mm_min: float) -> str:
        """Linear move at a feed (machine coordinates)."""

    @abstractmethod
    def dwell(self, seconds: float) -> list[str]: ...

    def render(self, blocks: list[str]) -> str:
        """The program text, one block per line."""
        return "\n".join(blocks) + "\n"


def words(axes_mm: Mapping[str, float], signed: bool = False) -> str:
    """``X100.000 Y-5.000`` (``X+100.000`` with ``signed``) for the axes given."""
    sign = "+" if signed else ""
    return " ".join(f"{axis}{value:{sign}.3f}" for axis, value in axes_mm.items())
