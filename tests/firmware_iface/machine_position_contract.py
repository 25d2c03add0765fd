"""The contract every machine-position source passes (``xmalign.roles.MachinePositionSource``).

A source gives the actual position in machine coordinates as mm, shape (3,);
says whether the machine stands still; raises a TransportError naming where it
reads from when that is gone; and plugs into OperatorPrompt as the position a
confirmed move is checked against. The checks take a ``stand`` fixture
(:class:`Stand`): test_machine_position_contract.py serves one per
implementation, tests/linuxcnc/test_real_linuxcnc_module.py a real headless LinuxCNC
read through LinuxCNC's own Python module.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pytest

from firmware_iface.machine_position import OperatorPrompt
from xmalign.errors import TransportError
from xmalign.roles import Clock, MachinePositionSource

SETTLE_S = 0.5


@dataclass
class Stand:
    """One implementation, served: its source, how to move the machine, how to cut it off."""

    source: MachinePositionSource
    place: Callable[[float, float, float], None]
    cut: Callable[[], None]
    #: Where the source reads from, as its errors name it.
    address: str
    clock: Clock
    #: False for a source that only ever sees a machine at rest (a position file).
    sees_motion: bool = True
    #: ``show_program(name, running)``: the controller has program ``name`` (its bare
    #: name, spelled as that controller does) running or idle; None: it reports none.
    show_program: Callable[[str, bool], None] | None = None
    #: Starts a move to (x, y, z) and returns while the machine is on its way (a
    #: controller that tells standstill from its own motion: LinuxCNC); None: ``place``
    #: (a source that sees motion as a reading that changes).
    move: Callable[[float, float, float], None] | None = None


def _settled(stand: Stand, reads: int = 10) -> bool:
    """Read the standstill on the virtual clock until it says yes (at most ``reads`` times)."""
    for _ in range(reads):
        if stand.source.is_standstill():
            return True
        stand.clock.sleep(SETTLE_S / 4)
    return False


def test_is_a_machine_position_source(stand: Stand) -> None:
    assert isinstance(stand.source, MachinePositionSource)


def test_gives_the_actual_position_in_mm_as_three_floats(stand: Stand) -> None:
    stand.place(1250.125, -300.5, 42.0)
    position = stand.source.position_mm()
    assert isinstance(position, np.ndarray) and position.shape == (3,)
    assert position.dtype == np.float64
    assert np.allclose(position, [1250.125, -300.5, 42.0], atol=1e-9)


def test_stands_still_once_the_position_stays_put(stand: Stand) -> None:
    stand.place(10.0, 20.0, 30.0)
    assert _settled(stand)
    assert isinstance(stand.source.is_standstill(), bool)


def test_a_moving_machine_does_not_stand_still(stand: Stand) -> None:
    if not stand.sees_motion:
        pytest.skip("a position file is written only with the machine at rest")
    stand.place(10.0, 20.0, 30.0)
    assert _settled(stand)
    move = stand.move or stand.place
    for step in range(1, 6):
        move(10.0 + step, 20.0, 30.0)  # 1 mm per read: moving
        assert not stand.source.is_standstill()
        stand.clock.sleep(SETTLE_S)
    assert _settled(stand)


def test_a_lost_source_is_a_transport_error_naming_it(stand: Stand) -> None:
    stand.cut()
    with pytest.raises(TransportError) as caught:
        stand.source.position_mm()
    assert stand.address in str(caught.value) and "\n" not in str(caught.value)


def test_an_operator_prompt_checks_the_confirmed_move_against_it(
    stand: Stand,
    reference_machine,  # noqa: ANN001
) -> None:
    target = np.array([1000.0, 750.0, -250.0])
    stand.place(100.0, 100.0, -100.0)
    presses: list[str] = []

    def press_enter(prompt: str) -> str:  # the machine arrives after the first Enter
        if presses:
            stand.place(*target)
        presses.append(prompt)
        return ""

    told: list[str] = []
    OperatorPrompt(reference_machine, press_enter, told.append, stand.source).move_to(target, 5e3)
    assert len(presses) == 2 and "move it there first" in told[-1]
    assert np.allclose(stand.source.position_mm(), target)
