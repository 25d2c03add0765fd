"""Is the program a followed controller runs xmalign's? Names as controllers spell them."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from xmalign.errors import DeviceError
from xmalign.program_check import ProgramGuard, program_name, same_program
from xmalign.roles import ProgramReport


@pytest.mark.parametrize(
    ("spelled", "bare"),
    [
        ("run", "RUN"),
        ("run.mpf", "RUN"),
        ("/home/cnc/linuxcnc/nc_files/run.ngc", "RUN"),  # LinuxCNC's adapter: the file
        ("/_N_MPF_DIR/_N_RUN_MPF", "RUN"),  # the SINUMERIK's NC notation
        ("/_N_WKS_DIR/_N_SHAFT_WPD/_N_PART_2_MPF", "PART_2"),  # a workpiece's program
        ("Sinumerik/FileSystem/Part Program/XMALIGN.MPF", "XMALIGN"),  # its OPC UA path
        ("O1234", "O1234"),  # a Fanuc's program number (the VMC sample agent)
        ("1234", "O1234"),  # the same number as some agents report it
        ("O01234", "O1234"),
        ("C:\\CNC\\Programs\\run.nc", "RUN"),
        (" run.ngc ", "RUN"),
        (".hidden", ".HIDDEN"),
    ],
)
def test_the_bare_name_of_a_program_however_a_controller_spells_it(spelled: str, bare: str) -> None:
    assert program_name(spelled) == bare


def test_different_programs_differ() -> None:
    assert same_program("/_N_MPF_DIR/_N_RUN_MPF", "Sinumerik/FileSystem/Part Program/run.mpf")
    assert not same_program("/_N_MPF_DIR/_N_OLD_MPF", "run")
    assert not same_program("/home/cnc/run2.ngc", "run")
    assert not same_program("O1000", "run")
    assert not same_program("O1001", "O1000")


@given(st.from_regex(r"[A-Za-z][A-Za-z0-9_]{0,20}", fullmatch=True))
def test_every_spelling_of_a_name_is_the_same_program(name: str) -> None:
    spellings = [
        name,
        f"{name}.ngc",
        f"/home/cnc/{name}.ngc",
        f"/_N_MPF_DIR/_N_{name.upper()}_MPF",
        f"Sinumerik/FileSystem/Part Program/{name}.mpf",
    ]
    assert all(same_program(spelled, name) for spelled in spellings), spellings


class Controller:
    name = "the test controller"

    def __init__(self, report: ProgramReport | None) -> None:
        self.report = report

    def program_report(self) -> ProgramReport | None:
        return self.report


def test_a_controller_that_does_not_report_its_program_is_told_once() -> None:
    told: list[str] = []
    guard = ProgramGuard(Controller(None), "run", "key", told.append)
    guard.check()
    guard.check()
    assert told == [
        "the test controller does not report its program: not checked against xmalign's"
        " program run (make sure it is the one running)"
    ]


@pytest.mark.parametrize("state", ["running", "paused"])
def test_another_program_running_or_stopped_mid_way_is_refused(state: str) -> None:
    guard = ProgramGuard(Controller(ProgramReport("O9999", state)), "run", "a.key", print)
    with pytest.raises(DeviceError) as caught:
        guard.check()
    assert str(caught.value) == (
        f"the test controller is {state} with program O9999, not xmalign's program run"
        " (a.key): a stale or wrong program; stop it and start xmalign's"
    )


def test_xmalign_s_program_or_an_idle_controller_passes() -> None:
    for report in [
        ProgramReport("/home/cnc/run.ngc", "running"),
        ProgramReport("O9999", "idle"),
        ProgramReport(None, "idle"),
    ]:
        ProgramGuard(Controller(report), "run", "key", print).check()
    with pytest.raises(DeviceError, match="with program .none., not xmalign's"):
        ProgramGuard(Controller(ProgramReport(None, "running")), "run", "key", print).check()
