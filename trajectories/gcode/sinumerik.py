"""Siemens Sinumerik 840D sl / 828D G-code.

``;`` comments, ``MSG("...")`` operator messages (cleared with ``MSG()``),
``G4 F..`` dwell in seconds (the F word means time only in the G4 block; the
programmed feed stays valid), ``G71`` metric, ``M0`` stop, ``M30`` end.
The start cancels radius compensation (``G40``) and the tool offset (``D0``).
Every move carries ``SUPA`` (block-wise suppression of the settable, programmable
and external zero offsets and of the DRF: machine coordinates). With
``cnc.work_offset`` the program writes the settable frame itself
(``$P_UIFR[n]=CTRANS(...)``), selects it and programs in it; retracts stay
``SUPA``.
"""

from __future__ import annotations

from collections.abc import Mapping

from trajectories.gcode.base import Dialect, plain_text, words
from xmalign.machine import AXES


class SinumerikDialect(Dialect):
    name = "sinumerik"

    def begin(self) -> list[str]:
        blocks = [f"; {plain_text(self.program_name)}", "G71 G90 G94 G17 G40", "D0"]
        if self.work_offset is not None:
            origin = ",".join(
                f"{axis},{value:.3f}"
                for axis, value in zip(AXES, self.work_offset.origin_mm, strict=True)
            )
            blocks += [
                f"$P_UIFR[{self.work_offset.number}]=CTRANS({origin})",
                self.work_offset.code,
            ]
        return blocks

    def end(self, retract_mm: Mapping[str, float]) -> list[str]:
        return [self.retract(retract_mm), "MSG()", "M30"]

    def _machine_word(self) -> str:
        return "" if self.work_offset is not None else "SUPA "

    def rapid(self, axes_mm: Mapping[str, float]) -> str:
        return f"{self._machine_word()}G0 {words(self.program_axes(axes_mm))}"

    def feed(self, axes_mm: Mapping[str, float], feed_mm_min: float) -> str:
        return f"{self._machine_word()}G1 {words(self.program_axes(axes_mm))} F{feed_mm_min:.1f}"

    def retract(self, axes_mm: Mapping[str, float]) -> str:
        return f"SUPA G0 {words(axes_mm)}"

    def comment(self, text: str) -> str:
        return f"; {plain_text(text)}"

    def message(self, text: str) -> str:
        return f'MSG("{plain_text(text)}")'

    def dwell(self, seconds: float) -> list[str]:
        return [f"G4 F{seconds:.3f}"]
