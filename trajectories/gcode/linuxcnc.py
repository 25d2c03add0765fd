"""LinuxCNC (rs274ngc) G-code.

``%`` delimiters, ``(comments)``, ``(MSG,...)`` operator messages, ``G4 P``
dwell in seconds, ``M0`` pause, ``M2`` end. The start cancels cutter radius
compensation, tool length offset and canned cycles (``G40 G49 G80``). Moves
carry ``G53`` (machine coordinates, non-modal; it works with G0 and G1).
With ``cnc.work_offset`` the program writes that offset itself (``G10 L2 P..
X.. Y.. Z.. R0``), suspends G92 offsets (``G92.2``), selects it and programs
in it; retracts stay in ``G53``.
"""

from __future__ import annotations

from collections.abc import Mapping

from trajectories.gcode.base import Dialect, plain_text, words


class LinuxCncDialect(Dialect):
    name = "linuxcnc"

    def begin(self) -> list[str]:
        blocks = ["%", f"({plain_text(self.program_name)})", "G21 G90 G94 G17 G40 G49 G80"]
        if self.work_offset is not None:
            number = self.work_offset.number
            blocks += [
                f"G10 L2 P{number} {self.offset_words()} R0",
                "G92.2",
                self.work_offset.code,
            ]
        return blocks

    def end(self, retract_mm: Mapping[str, float]) -> list[str]:
        return [self.retract(retract_mm), "M2", "%"]

    def _machine_word(self) -> str:
        return "" if self.work_offset is not None else "G53 "

    def rapid(self, axes_mm: Mapping[str, float]) -> str:
        return f"{self._machine_word()}G0 {words(self.program_axes(axes_mm))}"

    def feed(self, axes_mm: Mapping[str, float], feed_mm_min: float) -> str:
        return f"{self._machine_word()}G1 {words(self.program_axes(axes_mm))} F{feed_mm_min:.1f}"

    def retract(self, axes_mm: Mapping[str, float]) -> str:
        return f"G53 G0 {words(axes_mm)}"

    def comment(self, text: str) -> str:
        return f"({plain_text(text)})"

    def message(self, text: str) -> str:
        return f"(MSG,{plain_text(text)})"

    def dwell(self, seconds: float) -> list[str]:
        return [f"G4 P{seconds:.3f}"]
