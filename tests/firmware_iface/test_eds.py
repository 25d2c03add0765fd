"""The EDS against CiA 306: our checker, ``eds-validate`` (eds-utils) and canopen's EDS import."""

import shutil
import subprocess
from pathlib import Path

import canopen
import pytest

from firmware_iface.canopen_axis import EDS_PATH
from firmware_iface.eds_check import check_eds, main

OPTIONAL_OBJECTS = {
    0x1008, 0x1014, 0x1016, 0x1017, 0x1400, 0x1401, 0x1600, 0x1601, 0x1800, 0x1A00, 0x603F,
    0x6040, 0x6041, 0x605A, 0x6060, 0x6061, 0x6064, 0x606C, 0x607A, 0x607D, 0x6081, 0x6083,
    0x6085, 0x608F, 0x6098, 0x60FF, 0x6502,
}  # fmt: skip


def test_the_eds_is_clean():
    assert check_eds(EDS_PATH) == []
    assert main([str(EDS_PATH)]) == 0


#: eds-validate (eds-utils 0.3.1) reports an empty [ManufacturerObjects] as missing, although
#: CiA 306 counts it with SupportedObjects=0 and eds-utils' own writer writes it so.
EMPTY_MANUFACTURER_SECTION = "AUTO-FIXED: Section [ManufacturerObjects] was missing"


EDS_VALIDATE = shutil.which("eds-validate")
needs_eds_validate = pytest.mark.skipif(
    EDS_VALIDATE is None,
    reason="eds-validate (PyPI eds-utils) is not installed; .ci/run installs it",
)
#: eds-utils' writer, run by the interpreter eds-validate runs on (eds-utils is kept out of
#: the test environment: it installs a top-level package named "tests").
WRITE_BACK = """
import sys
from eds_utils.core.file_io.read_eds import read_eds
from eds_utils.core.file_io.write_eds import write_eds
write_eds(read_eds(sys.argv[1])[0], sys.argv[2])
"""


def _eds_validate(path: Path) -> list[str]:
    assert EDS_VALIDATE is not None
    found = subprocess.run([EDS_VALIDATE, str(path)], capture_output=True, text=True)
    return [line for line in found.stderr.splitlines() if line.strip()]


@needs_eds_validate
def test_eds_validate_finds_nothing_but_its_own_empty_section_false_positive(tmp_path):
    assert _eds_validate(EDS_PATH) == [EMPTY_MANUFACTURER_SECTION]
    # the same finding for the file eds-utils itself writes from ours
    assert EDS_VALIDATE is not None
    python = Path(EDS_VALIDATE).resolve().parent / "python"
    written = tmp_path / "written.eds"
    subprocess.run([str(python), "-c", WRITE_BACK, str(EDS_PATH), str(written)], check=True)
    assert "[ManufacturerObjects]\nSupportedObjects=0" in written.read_text()
    assert _eds_validate(written) == [EMPTY_MANUFACTURER_SECTION]


@needs_eds_validate
def test_eds_validate_finds_a_damaged_object_list(tmp_path):
    path = damaged(tmp_path, "27=0x6502\n", "")
    assert any("0x6502" in line for line in _eds_validate(path))


def test_canopen_imports_it_with_every_listed_object_and_the_pdo_mapping():
    od = canopen.import_od(str(EDS_PATH), 4)
    assert {index for index in (o.index for o in od.values())} == OPTIONAL_OBJECTS | {
        0x1000,
        0x1001,
        0x1018,
    }
    # profile position, homing, cyclic synchronous velocity
    assert od[0x6502].default == 0x0001 | 0x0020 | 0x0100
    # RPDO 1 the controlword alone, RPDO 2 the target position alone: a PDO never carries a
    # stale copy of an object the host wrote otherwise (canopen's BaseNode402 sends RPDO 1)
    assert [od[0x1400][1].default, od[0x1401][1].default, od[0x1800][1].default] == [
        0x204,
        0x304,
        0x184,
    ]
    assert [od[0x1600][0].default, od[0x1600][1].default] == [1, 0x60400010]
    assert [od[0x1601][0].default, od[0x1601][1].default] == [1, 0x607A0020]
    assert [od[0x1A00][s].default for s in (1, 2)] == [0x60410010, 0x60640020]
    assert od.device_information.nr_of_RXPDO == 2 and od.device_information.nr_of_TXPDO == 1
    assert od[0x1014].default == 0x84  # EMCY
    assert (od[0x6081].min, od[0x6081].max) == (1, od[0x6081].default)


def damaged(tmp_path: Path, old: str, new: str) -> Path:
    text = EDS_PATH.read_text(encoding="ascii")
    assert old in text
    path = tmp_path / "damaged.eds"
    path.write_text(text.replace(old, new, 1), encoding="ascii")
    return path


@pytest.mark.parametrize(
    ("old", "new", "problem"),
    [
        ("SupportedObjects=27\n", "SupportedObjects=26\n", "numbered 1..26"),
        ("27=0x6502\n", "", "numbered 1..27"),
        ("[6502]\nParameterName", "[6503]\nParameterName", "6502] listed in [OptionalObjects]"),
        ("NrOfRXPDO=2", "NrOfRXPDO=1", "NrOfRXPDO=1 but 2"),
        ("SubNumber=5\n\n[1800sub0]", "SubNumber=4\n\n[1800sub0]", "SubNumber=4 but 5"),
        ("DefaultValue=0x60640020", "DefaultValue=0x60640010", "with 16 bits"),
        ("DefaultValue=0x607A0020", "DefaultValue=0x60980008", "PDOMapping=0"),
        ("AccessType=rww", "AccessType=write", "AccessType=write"),
        (
            "DataType=0x0005\nAccessType=ro\nDefaultValue=0\nPDOMapping=1",
            "DataType=0x0005\nAccessType=ro\nDefaultValue=300\nPDOMapping=1",
            "does not fit UNSIGNED8",
        ),
        ("CreationDate=01-01-2025", "CreationDate=2025-01-01", "CreationDate"),
        ("EDSVersion=4.0", "EDSVersion=3.0", "EDSVersion must be 4.0"),
        ("[DummyUsage]", "[Dummies]", "[DummyUsage] section missing"),
        ("27=0x6502\n", "27=0x2502\n", "0x2502 does not belong in this list"),
        ("HighLimit=699051", "HighLimit=600000", "DefaultValue=699051 outside LowLimit..HighLimit"),
        ("LowLimit=1", "LowLimit=800000", "LowLimit=800000 above HighLimit=699051"),
        ("LowLimit=1", "LowLimit=-1", "LowLimit=-1 does not fit UNSIGNED32"),
        (
            "DataType=0x0007\nAccessType=ro\nDefaultValue=0x00000121",
            "DataType=0x0030\nAccessType=ro\nDefaultValue=0x00000121",
            "DataType 0x0030 unknown",
        ),
        ("ObjectType=0x7\nDataType=0x0009", "ObjectType=0x3\nDataType=0x0009", "is not VAR"),
        ("[1A00]\n", "[1A01]\n", "no mapping object 0x1A00"),
        (
            "[1016sub0]\nParameterName=Highest sub-index supported\nObjectType=0x7\nDataType=0x0005"
            "\nAccessType=ro\nDefaultValue=1",
            "[1016sub0]\nParameterName=Highest sub-index supported"
            "\nObjectType=0x7\nDataType=0x0005\nAccessType=ro\nDefaultValue=2",
            "highest sub-index",
        ),
    ],
)
def test_the_checker_finds_each_kind_of_defect(tmp_path, old, new, problem):
    problems = check_eds(damaged(tmp_path, old, new))
    assert any(problem in p for p in problems), problems


def test_a_device_without_a_baud_rate_is_flagged(tmp_path):
    text = EDS_PATH.read_text(encoding="ascii").replace("BaudRate_500=1", "BaudRate_500=0")
    path = tmp_path / "silent.eds"
    path.write_text(text.replace("BaudRate_1000=1", "BaudRate_1000=0"), encoding="ascii")
    assert "[DeviceInfo] supports no baud rate" in check_eds(path)
    assert main([str(path)]) == 1
