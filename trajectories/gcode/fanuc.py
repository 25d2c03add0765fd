"""ISO / Fanuc G-code (Fanuc Series 0i/30i programming manual conventions).

``%`` tape marks, an ``O`` program number, ``(comments)``, ``G04 P`` dwell in
milliseconds (integer, valid whatever the decimal-point setting), ``M00``
stop and ``M30`` end. Coordinates always carry a decimal point, so a control
with "calculator-type" input off still reads millimetres.
"""

from __future__ import annotations

from collections.abc import Mapping

from trajectories.gcode.base import Dialect, plain_text, words


class IsoDialect(Dialect):
    name = "iso"

    def begin(self) -> list[str]:
        return ["%", f"O1000 ({plain_text(self.program_name)})", "G21 G90 G94 G17"]

    def end(self, retract_mm: Mapping[str, float]) -> list[str]:
        return [self.rapid(retract_mm), "M30", "%"]

    def comment(self, text: str) -> str:
        return f"({plain_text(text)})"

    def message(self, text: str) -> str:
        return self.comment(text)

    def stop(self) -> str:
        return "M00"

    def rapid(self, axes_mm: Mapping[str, float]) -> str:
        return f"G00 {words(axes_mm)}"

    def feed(self, axes_mm: Mapping[str, float], feed_mm_min: float) -> str:
        return f"G01 {words(axes_mm)} F{feed_mm_min:.1f}"

    def dwell(self, seconds: float) -> list[str]:
        return [f"G04 P{round(seconds * 1000.0)}"]
