"""What a controller connection reports in one read: position, program state, its own words.

Shared by the read-only controller connections (:mod:`firmware_iface.mtconnect`,
:mod:`firmware_iface.sinumerik_opcua`). ``program_state`` uses the three words of
the ``ProgramControl`` role (``idle``, ``running``, ``paused``); ``state`` keeps
the controller's own word for the operator (``FEED_HOLD``, ``progStatus 2
(stopped)``).
"""

from __future__ import annotations

from dataclasses import dataclass

from xmalign.geometry import Vec
from xmalign.roles import ProgramState


@dataclass(frozen=True)
class ControllerStatus:
    """One reading of a controller.

    Attributes
    ----------
    position_mm : ndarray, shape (3,)
        Actual position in machine coordinates, mm (converted from the
        controller's unit).
    program_state : {"idle", "running", "paused"}
    state : str
        The controller's own word for it, for messages.
    mode : str or None
        The controller's operating mode (``AUTOMATIC``, ``MANUAL_DATA_INPUT``…), None
        when it does not report one.
    """

    position_mm: Vec
    program_state: ProgramState
    state: str
    mode: str | None = None
