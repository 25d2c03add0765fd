"""LinuxCNC (rs274ngc) G-code.

``%`` delimiters, ``(comments)``, ``(MSG,...)`` operator messages, ``G4 P``
dwell in seconds, ``M0`` pause, ``M2`` end.
"""

from __future__ import annotations

from collections.abc import Mapping

from trajectories.gcode.base import Dialect, plain_text


class LinuxCncDialect(Dialect):
    name = "linuxcnc"

    def begin(self) -> list[str]:
        return ["%", f"({plain_text(self.program_name)})", "G21 G90 G94 G17"]

    def end(self, retract_mm: Mapping[str, float]) -> list[str]:
        return [self.rapid(retract_mm), "M2", "%"]

    def comment(self, text: str) -> str:
        return f"({plain_text(text)})"

    def message(self, text: str) -> str:
        return f"(MSG,{plain_text(text)})"

    def dwell(self, seconds: float) -> list[str]:
        return [f"G4 P{seconds:.3f}"]
