"""ISO / Fanuc G-code (Fanuc Series 0i/30i programming manual conventions).

``%`` tape marks, an ``O`` program number, ``(comments)``, ``G04 P`` dwell in
milliseconds (integer, valid whatever the decimal-point setting), ``M00``
stop and ``M30`` end. Coordinates always carry a decimal point, so a control
with "calculator-type" input off still reads millimetres.

Fanuc's ``G53`` moves at rapid traverse only, so the measuring moves run in a
work offset the program sets itself: ``G10 L2 P6 X0 Y0 Z0`` and ``G59`` (or
the machine file's ``cnc.work_offset``, origin written the same way), after
``G40 G49 G80`` (radius, length, cycles off) and ``G52 X0 Y0 Z0`` (local
coordinate system off). The external work offset must be zero (it cannot be
cancelled without overwriting it). Retracts are ``G53 G00`` (machine
coordinates).
"""

from __future__ import annotations

from collections.abc import Mapping

from trajectories.gcode.base import Dialect, plain_text, words
from xmalign.machine import WorkOffset

#: The number of every program xmalign writes for a Fanuc (its file name does not count there).
PROGRAM_NUMBER = "O1000"

#: The work offset the program sets when the machine file gives none: G59 at machine zero.
DEFAULT_WORK_OFFSET = WorkOffset(code="G59", origin_mm=[0.0, 0.0, 0.0])


class IsoDialect(Dialect):
    name = "iso"

    def __init__(
        self,
        program_name: str = "XMALIGN",
        work_offset: WorkOffset | None = None,
        stop_at_points: bool = False,
    ) -> None:
        super().__init__(program_name, work_offset or DEFAULT_WORK_OFFSET, stop_at_points)

    def begin(self) -> list[str]:
        assert self.work_offset is not None
        return [
            "%",
            f"{PROGRAM_NUMBER} ({plain_text(self.program_name)})",
            "G21 G90 G94 G17 G40 G49 G80",
            "G52 X0. Y0. Z0.",
            f"G10 L2 P{self.work_offset.number} {self.offset_words()}",
            self.work_offset.code,
        ]

    def end(self, retract_mm: Mapping[str, float]) -> list[str]:
        return [self.retract(retract_mm), "M30", "%"]

    def comment(self, text: str) -> str:
        return f"({plain_text(text)})"

    def message(self, text: str) -> str:
        return self.comment(text)

    def stop(self) -> str:
        return "M00"

    def rapid(self, axes_mm: Mapping[str, float]) -> str:
        return f"G00 {words(self.program_axes(axes_mm))}"

    def feed(self, axes_mm: Mapping[str, float], feed_mm_min: float) -> str:
        return f"G01 {words(self.program_axes(axes_mm))} F{feed_mm_min:.1f}"

    def retract(self, axes_mm: Mapping[str, float]) -> str:
        return f"G53 G00 {words(axes_mm)}"

    def dwell(self, seconds: float) -> list[str]:
        return [f"G04 P{round(seconds * 1000.0)}"]
