"""The interface every G-code dialect implements.

A dialect turns abstract steps (move, dwell, comment, message, stop) into the
blocks of its controller. Coordinates are absolute metric CNC tool-point
coordinates (mm), feeds mm/min, dwell times s.
"""

from __future__ import annotations

import re
from abc import ABC, abstractmethod
from collections.abc import Mapping

#: Characters a comment or message may keep; the rest (parentheses, quotes) end comments.
_UNSAFE = re.compile(r"[^A-Za-z0-9 .,:;+\-=/_%#*]")


def plain_text(text: str) -> str:
    """``text`` without characters that would end a comment or message early."""
    return _UNSAFE.sub("", text)


class Dialect(ABC):
    """Spelling of one controller's G-code; each method returns whole blocks."""

    #: Dialect name as used by ``--dialect``.
    name: str = ""

    def __init__(self, program_name: str = "XMALIGN") -> None:
        self.program_name = program_name

    @abstractmethod
    def begin(self) -> list[str]:
        """Program start: name, metric, absolute, feed per minute."""

    @abstractmethod
    def end(self, retract_mm: Mapping[str, float]) -> list[str]:
        """Rapid retract to ``retract_mm`` and program end."""

    @abstractmethod
    def comment(self, text: str) -> str: ...

    @abstractmethod
    def message(self, text: str) -> str:
        """A message the controller shows to the operator (a comment where it has none)."""

    def stop(self) -> str:
        """Programmed stop; the operator continues with cycle start."""
        return "M0"

    def rapid(self, axes_mm: Mapping[str, float]) -> str:
        """Rapid move of the named axes (``{"X": .., "Z": ..}``)."""
        return f"G0 {words(axes_mm)}"

    def feed(self, axes_mm: Mapping[str, float], feed_mm_min: float) -> str:
        """Linear move at a feed."""
        return f"G1 {words(axes_mm)} F{feed_mm_min:.1f}"

    @abstractmethod
    def dwell(self, seconds: float) -> list[str]: ...

    def render(self, blocks: list[str]) -> str:
        """The program text, one block per line."""
        return "\n".join(blocks) + "\n"


def words(axes_mm: Mapping[str, float], signed: bool = False) -> str:
    """``X100.000 Y-5.000`` (``X+100.000`` with ``signed``) for the axes given."""
    sign = "+" if signed else ""
    return " ".join(f"{axis}{value:{sign}.3f}" for axis, value in axes_mm.items())
