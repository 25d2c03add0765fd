"""Heidenhain TNC conversational (Klartext) programs.

Numbered blocks from ``0 BEGIN PGM name MM`` to ``END PGM name MM``, straight
lines ``L X+.. Y+.. Z+.. R0 F..`` (``FMAX`` for rapid), ``;`` comment blocks,
dwell with cycle 9 (``CYCL DEF 9.0 DWELL TIME`` / ``CYCL DEF 9.1 DWELL t``,
active as soon as it is defined), ``STOP`` and ``M30``. The TNC has no plain
operator message block, so messages are comments.
"""

from __future__ import annotations

from collections.abc import Mapping

from trajectories.gcode.base import Dialect, plain_text, words


class HeidenhainDialect(Dialect):
    name = "heidenhain"

    @property
    def _pgm(self) -> str:
        return plain_text(self.program_name).replace(" ", "_")

    def begin(self) -> list[str]:
        return [f"BEGIN PGM {self._pgm} MM"]

    def end(self, retract_mm: Mapping[str, float]) -> list[str]:
        # The TNC ends a program with M2/M30 on the last positioning block.
        return [f"{self.rapid(retract_mm)} M30", f"END PGM {self._pgm} MM"]

    def comment(self, text: str) -> str:
        return f"; {plain_text(text)}"

    def message(self, text: str) -> str:
        return self.comment(text)

    def stop(self) -> str:
        return "STOP"

    def rapid(self, axes_mm: Mapping[str, float]) -> str:
        return f"L {words(axes_mm, signed=True)} R0 FMAX"

    def feed(self, axes_mm: Mapping[str, float], feed_mm_min: float) -> str:
        return f"L {words(axes_mm, signed=True)} R0 F{round(feed_mm_min)}"

    def dwell(self, seconds: float) -> list[str]:
        return ["CYCL DEF 9.0 DWELL TIME", f"CYCL DEF 9.1 DWELL {seconds:.3f}"]

    def render(self, blocks: list[str]) -> str:
        return "".join(f"{number} {block}\n" for number, block in enumerate(blocks))
