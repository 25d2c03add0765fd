"""Heidenhain TNC conversational (Klartext) programs.

Numbered blocks from ``0 BEGIN PGM name MM`` to ``END PGM name MM`` (the name
is the file name without extension), straight lines ``L X+.. Y+.. Z+.. R0 F..``
(``FMAX`` for rapid), ``;`` comment blocks, dwell with cycle 9 (``CYCL DEF 9.0
DWELL TIME`` / ``CYCL DEF 9.1 DWELL t``, active as soon as it is defined),
``STOP`` and ``M30``. The TNC has no plain operator message block, so messages
are comments.

``TOOL CALL 0 Z`` at the start cancels the tool length compensation (a tool of
length 0); ``R0`` in every block keeps radius compensation off; ``M91`` on
every positioning block makes its coordinates refer to the machine datum. A
work offset is neither needed nor supported.
"""

from __future__ import annotations

from collections.abc import Mapping

from trajectories.gcode.base import Dialect, plain_text, words
from xmalign.errors import InputError
from xmalign.machine import WorkOffset


class HeidenhainDialect(Dialect):
    name = "heidenhain"

    def __init__(
        self,
        program_name: str = "XMALIGN",
        work_offset: WorkOffset | None = None,
        stop_at_points: bool = False,
    ) -> None:
        if work_offset is not None:
            raise InputError(
                "cnc.work_offset: the heidenhain dialect moves with M91 (machine datum) and"
                " takes no work offset; remove the key"
            )
        super().__init__(program_name, None, stop_at_points)

    @property
    def _pgm(self) -> str:
        return plain_text(self.program_name).replace(" ", "_")

    def begin(self) -> list[str]:
        return [f"BEGIN PGM {self._pgm} MM", "TOOL CALL 0 Z"]

    def end(self, retract_mm: Mapping[str, float]) -> list[str]:
        # The TNC ends a program with M2/M30 on the last positioning block.
        return [f"{self.retract(retract_mm)} M30", f"END PGM {self._pgm} MM"]

    def comment(self, text: str) -> str:
        return f"; {plain_text(text)}"

    def message(self, text: str) -> str:
        return self.comment(text)

    def stop(self) -> str:
        return "STOP"

    def rapid(self, axes_mm: Mapping[str, float]) -> str:
        return f"L {words(axes_mm, signed=True)} R0 FMAX M91"

    def feed(self, axes_mm: Mapping[str, float], feed_mm_min: float) -> str:
        return f"L {words(axes_mm, signed=True)} R0 F{round(feed_mm_min)} M91"

    def retract(self, axes_mm: Mapping[str, float]) -> str:
        return self.rapid(axes_mm)

    def dwell(self, seconds: float) -> list[str]:
        return ["CYCL DEF 9.0 DWELL TIME", f"CYCL DEF 9.1 DWELL {seconds:.3f}"]

    def render(self, blocks: list[str]) -> str:
        return "".join(f"{number} {block}\n" for number, block in enumerate(blocks))
