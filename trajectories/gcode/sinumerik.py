"""Siemens Sinumerik 840D sl / 828D G-code.

``;`` comments, ``MSG("...")`` operator messages (cleared with ``MSG()``),
``G4 F..`` dwell in seconds (the F word means time only in the G4 block; the
programmed feed stays valid), ``G71`` metric, ``M0`` stop, ``M30`` end.
"""

from __future__ import annotations

from collections.abc import Mapping

from trajectories.gcode.base import Dialect, plain_text


class SinumerikDialect(Dialect):
    name = "sinumerik"

    def begin(self) -> list[str]:
        return [f"; {plain_text(self.program_name)}", "G71 G90 G94 G17"]

    def end(self, retract_mm: Mapping[str, float]) -> list[str]:
        return [self.rapid(retract_mm), "MSG()", "M30"]

    def comment(self, text: str) -> str:
        return f"; {plain_text(text)}"

    def message(self, text: str) -> str:
        return f'MSG("{plain_text(text)}")'

    def dwell(self, seconds: float) -> list[str]:
        return [f"G4 F{seconds:.3f}"]
