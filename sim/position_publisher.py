"""Publish a controller's actual position to a file the simulated instruments follow.

``xmalign sim publish-position FILE`` runs on the LinuxCNC computer: it reads
LinuxCNC's actual position (machine coordinates, mm) through LinuxCNC's own
Python module every ``period_s`` and replaces FILE (write, then rename) by one
line ``x y z`` whenever it changed; ``xmalign sim serve --follow-position-file
FILE`` then carries the virtual receiver where the real machine stands. It ends
by itself when LinuxCNC stops: every read takes a fresh status (a status
opened while LinuxCNC ran keeps answering from its shared memory after
LinuxCNC has gone, which kept the tests' first publisher running for ever).
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

import numpy as np

from xmalign.errors import TransportError
from xmalign.roles import MachinePositionSource

#: How often the position is read by default, s.
PUBLISH_PERIOD_S = 0.005


def position_line(position_mm: np.ndarray) -> str:
    """The file's one line: ``x y z`` in mm, 6 decimals."""
    x, y, z = np.asarray(position_mm, dtype=float)
    return f"{x:.6f} {y:.6f} {z:.6f}\n"


def write_position(path: Path, text: str) -> None:
    """Replace ``path`` by ``text`` at once (a reader never sees half a line); mode 0644."""
    part = path.with_name(path.name + ".part")
    part.write_text(text, encoding="ascii")
    part.chmod(0o644)
    os.replace(part, path)


def publish_positions(
    source: MachinePositionSource,
    path: Path,
    stop: threading.Event,
    period_s: float = PUBLISH_PERIOD_S,
) -> str:
    """Keep ``path`` at the position of ``source`` until it cannot be read or ``stop`` is set.

    Returns why it ended: the source's error (the controller has stopped) or
    ``'stopped'``.
    """
    written = None
    while not stop.is_set():
        try:
            text = position_line(source.position_mm())
        except TransportError as error:
            return str(error)
        if text != written:
            write_position(path, text)
            written = text
        stop.wait(period_s)
    return "stopped"
