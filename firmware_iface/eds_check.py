"""A checker of CANopen EDS files against the rules of CiA 306 (EDS format 4.0).

The project checks its EDS with this module, with ``eds-validate`` (PyPI
``eds-utils``) and with the ``canopen`` library's own EDS import. Rules
(docs/canopen-axis.md, "Checking the EDS"):

* the sections [FileInfo], [DeviceInfo], [DummyUsage], [MandatoryObjects],
  [OptionalObjects], [ManufacturerObjects] with their required keys and value
  formats (dates mm-dd-yyyy, times hh:mm(AM|PM), booleans 0/1, EDSVersion 4.0);
* every object is listed in exactly one object list, every listed object has a
  section, ``SupportedObjects`` counts the entries 1..N; mandatory objects are
  0x1000, 0x1001, 0x1018; optional ones lie in 0x1000–0x1FFF or 0x6000–0xFFFF,
  manufacturer ones in 0x2000–0x5FFF;
* a VAR has a known DataType, an AccessType of ro/wo/rw/rwr/rww/const, a
  PDOMapping of 0/1 and a DefaultValue that fits its type and lies within its
  LowLimit and HighLimit (which fit the type too); an ARRAY or RECORD
  has as many sub-object sections as ``SubNumber`` says, and sub-index 0 is an
  UNSIGNED8 whose default is the highest sub-index;
* NrOfRXPDO / NrOfTXPDO count the PDO communication objects, each has its
  mapping object, and every mapped object exists, may be mapped and has the
  length of its type (64 bits at most in one PDO).

Run it as ``python -m firmware_iface.eds_check FILE.eds`` (exit 1 on a problem).
"""

from __future__ import annotations

import configparser
import re
import sys
from pathlib import Path

#: CiA 301 data types: index -> (name, bits); strings and domains have no fixed length.
DATA_TYPES = {
    0x01: ("BOOLEAN", 1),
    0x02: ("INTEGER8", 8),
    0x03: ("INTEGER16", 16),
    0x04: ("INTEGER32", 32),
    0x05: ("UNSIGNED8", 8),
    0x06: ("UNSIGNED16", 16),
    0x07: ("UNSIGNED32", 32),
    0x08: ("REAL32", 32),
    0x09: ("VISIBLE_STRING", 0),
    0x0A: ("OCTET_STRING", 0),
    0x0B: ("UNICODE_STRING", 0),
    0x0F: ("DOMAIN", 0),
    0x11: ("REAL64", 64),
    0x15: ("INTEGER64", 64),
    0x1B: ("UNSIGNED64", 64),
}
_SIGNED = {0x02, 0x03, 0x04, 0x15}
ACCESS_TYPES = {"ro", "wo", "rw", "rwr", "rww", "const"}
VAR, ARRAY, RECORD = 0x7, 0x8, 0x9
MANDATORY = {0x1000, 0x1001, 0x1018}
_FILE_INFO: tuple[str, ...] = ("FileName", "FileVersion", "FileRevision", "EDSVersion")
_FILE_INFO += ("Description", "CreationTime", "CreationDate", "CreatedBy")
_DEVICE_INFO: tuple[str, ...] = ("VendorName", "VendorNumber", "ProductName", "ProductNumber")
_DEVICE_INFO += ("RevisionNumber", "OrderCode", "Granularity", "NrOfRXPDO", "NrOfTXPDO")
_BOOLEANS = tuple(f"BaudRate_{rate}" for rate in (10, 20, 50, 125, 250, 500, 800, 1000))
_BOOLEANS += ("SimpleBootUpMaster", "SimpleBootUpSlave", "DynamicChannelsSupported")
_BOOLEANS += ("GroupMessaging", "LSS_Supported")
_DATE = re.compile(r"^(0[1-9]|1[0-2])-(0[1-9]|[12]\d|3[01])-\d{4}$")
_TIME = re.compile(r"^(0\d|1[0-2]):[0-5]\d(AM|PM)$")
_OBJECT = re.compile(r"^([0-9A-F]{4})$")
_SUB = re.compile(r"^([0-9A-F]{4})SUB([0-9A-F]{1,2})$")


def _int(text: str) -> int:
    """An EDS integer: decimal, 0x hex or 0 octal; ``$NODEID`` counts as 1."""
    text = text.strip().upper().replace("$NODEID", "1")
    return sum(int(term, 0) for term in text.split("+"))


class _Checker:
    def __init__(self, text: str) -> None:
        self.eds = configparser.ConfigParser(interpolation=None, strict=True)
        self.eds.optionxform = str.lower  # type: ignore[assignment,method-assign]
        self.eds.read_string(text)
        self.sections = {name.upper(): self.eds[name] for name in self.eds.sections()}
        self.problems: list[str] = []

    def fail(self, where: str, message: str) -> None:
        self.problems.append(f"[{where}] {message}")

    def get(self, section: str, key: str) -> str | None:
        values = self.sections.get(section.upper())
        return None if values is None else values.get(key.lower())

    def require(self, section: str, key: str) -> str | None:
        value = self.get(section, key)
        if value is None:
            self.fail(section, f"missing {key}")
        return value

    def integer(self, section: str, key: str, low: int, high: int) -> int | None:
        value = self.require(section, key)
        if value is None:
            return None
        try:
            number = _int(value)
        except ValueError:
            self.fail(section, f"{key}={value} is not a number")
            return None
        if not low <= number <= high:
            self.fail(section, f"{key}={value} outside {low}..{high}")
        return number

    # --- sections -------------------------------------------------------------------------
    def run(self) -> list[str]:
        for name in ("FileInfo", "DeviceInfo", "DummyUsage", "MandatoryObjects"):
            if name.upper() not in self.sections:
                self.fail(name, "section missing")
        if self.problems:
            return self.problems
        self.file_info()
        self.device_info()
        listed = self.object_lists()
        self.objects(listed)
        self.pdos()
        return self.problems

    def file_info(self) -> None:
        for key in _FILE_INFO:
            self.require("FileInfo", key)
        self.integer("FileInfo", "FileVersion", 0, 255)
        self.integer("FileInfo", "FileRevision", 0, 255)
        if self.get("FileInfo", "EDSVersion") not in (None, "4.0"):
            self.fail("FileInfo", "EDSVersion must be 4.0")
        for key, pattern in (
            ("CreationDate", _DATE),
            ("ModificationDate", _DATE),
            ("CreationTime", _TIME),
            ("ModificationTime", _TIME),
        ):
            value = self.get("FileInfo", key)
            if value is not None and not pattern.match(value):
                self.fail("FileInfo", f"{key}={value} is not in the CiA 306 format")

    def device_info(self) -> None:
        for key in _DEVICE_INFO:
            self.require("DeviceInfo", key)
        for key in _BOOLEANS:
            self.integer("DeviceInfo", key, 0, 1)
        self.integer("DeviceInfo", "Granularity", 0, 64)
        if not any(self.get("DeviceInfo", key) == "1" for key in _BOOLEANS[:8]):
            self.fail("DeviceInfo", "supports no baud rate")
        for n in range(1, 8):
            self.integer("DummyUsage", f"Dummy{n:04d}", 0, 1)

    def object_lists(self) -> dict[int, str]:
        listed: dict[int, str] = {}
        for name in ("MandatoryObjects", "OptionalObjects", "ManufacturerObjects"):
            if name.upper() not in self.sections:
                continue
            count = self.integer(name, "SupportedObjects", 0, 0xFFFF) or 0
            keys = set(self.sections[name.upper()]) - {"supportedobjects"}
            if keys != {str(n) for n in range(1, count + 1)}:
                self.fail(name, f"entries must be numbered 1..{count} (SupportedObjects)")
            for n in range(1, count + 1):
                index = self.integer(name, str(n), 0x1000, 0xFFFF)
                if index is None:
                    continue
                if index in listed:
                    self.fail(name, f"0x{index:04X} is listed twice")
                listed[index] = name
                self.object_range(name, index)
        return listed

    def object_range(self, list_name: str, index: int) -> None:
        ok = {
            "MandatoryObjects": index in MANDATORY,
            "OptionalObjects": index not in MANDATORY
            and (0x1000 <= index <= 0x1FFF or 0x6000 <= index <= 0xFFFF),
            "ManufacturerObjects": 0x2000 <= index <= 0x5FFF,
        }[list_name]
        if not ok:
            self.fail(list_name, f"0x{index:04X} does not belong in this list")

    def objects(self, listed: dict[int, str]) -> None:
        present = {int(m.group(1), 16) for s in self.sections if (m := _OBJECT.match(s))}
        for index in sorted(MANDATORY - present):
            self.fail(f"{index:04X}", "mandatory object missing")
        for index in sorted(set(listed) - present):
            self.fail(f"{index:04X}", f"listed in [{listed[index]}] but has no section")
        for index in sorted(present - set(listed)):
            self.fail(f"{index:04X}", "not listed in any object list")
        subs: dict[int, set[int]] = {}
        for section in self.sections:
            if m := _SUB.match(section):
                subs.setdefault(int(m.group(1), 16), set()).add(int(m.group(2), 16))
        for index in sorted(set(subs) - present):
            self.fail(f"{index:04X}", "sub-objects of an object without a section")
        for index in sorted(present):
            self.one_object(index, subs.get(index, set()))

    def one_object(self, index: int, subs: set[int]) -> None:
        name = f"{index:04X}"
        parameter = self.require(name, "ParameterName")
        if parameter is not None and len(parameter) > 241:
            self.fail(name, "ParameterName longer than 241 characters")
        object_type = self.integer(name, "ObjectType", 0, 0x9)
        if object_type == VAR:
            if subs:
                self.fail(name, "a VAR has no sub-objects")
            self.variable(name)
        elif object_type in (ARRAY, RECORD):
            self.structure(name, subs)
        elif object_type is not None:
            self.fail(name, f"ObjectType {object_type:#x} is not VAR, ARRAY or RECORD")

    def structure(self, name: str, subs: set[int]) -> None:
        count = self.integer(name, "SubNumber", 1, 255)
        if count is not None and count != len(subs):
            self.fail(name, f"SubNumber={count} but {len(subs)} sub-object sections")
        if 0 not in subs:
            self.fail(name, "sub-index 0 missing")
            return
        sub0 = f"{name}sub0"
        if (
            self.get(sub0, "DataType") not in (None,)
            and _int(self.get(sub0, "DataType") or "0") != 5
        ):
            self.fail(sub0, "sub-index 0 must be UNSIGNED8")
        default = self.get(sub0, "DefaultValue")
        if default is not None and _int(default) != max(subs):
            self.fail(sub0, f"DefaultValue={default} but the highest sub-index is {max(subs)}")
        for sub in sorted(subs):
            section = f"{name}sub{sub:X}"
            self.require(section, "ParameterName")
            if self.integer(section, "ObjectType", 0x7, 0x7) is not None:
                self.variable(section)

    def variable(self, name: str) -> None:
        data_type = self.integer(name, "DataType", 0, 0xFFFF)
        if data_type is not None and data_type not in DATA_TYPES:
            self.fail(name, f"DataType {data_type:#06x} unknown")
        access = self.require(name, "AccessType")
        if access is not None and access.lower() not in ACCESS_TYPES:
            self.fail(name, f"AccessType={access} is not one of {sorted(ACCESS_TYPES)}")
        self.integer(name, "PDOMapping", 0, 1)
        if data_type in DATA_TYPES:
            values = {
                key: self.fitting(name, key, data_type)
                for key in ("DefaultValue", "LowLimit", "HighLimit")
            }
            self.within_limits(name, values)

    def fitting(self, name: str, key: str, data_type: int) -> int | None:
        """The integer value of ``key`` if it is given and fits ``data_type`` (else None)."""
        text = self.get(name, key)
        bits = DATA_TYPES[data_type][1]
        if text is None or bits == 0 or data_type in (0x08, 0x11):
            return None
        try:
            value = _int(text)
        except ValueError:
            self.fail(name, f"{key}={text} is not a number")
            return None
        low, high = (
            (-(1 << (bits - 1)), (1 << (bits - 1)) - 1)
            if data_type in _SIGNED
            else (0, (1 << bits) - 1)
        )
        if not low <= value <= high:
            self.fail(name, f"{key}={text} does not fit {DATA_TYPES[data_type][0]}")
            return None
        return value

    def within_limits(self, name: str, values: dict[str, int | None]) -> None:
        low, high, default = values["LowLimit"], values["HighLimit"], values["DefaultValue"]
        if low is not None and high is not None and low > high:
            self.fail(name, f"LowLimit={low} above HighLimit={high}")
        if default is not None and (
            (low is not None and default < low) or (high is not None and default > high)
        ):
            self.fail(name, f"DefaultValue={default} outside LowLimit..HighLimit")

    def pdos(self) -> None:
        for kind, first_comm, first_map in (("RX", 0x1400, 0x1600), ("TX", 0x1800, 0x1A00)):
            comms = [
                i for i in range(first_comm, first_comm + 0x200) if f"{i:04X}" in self.sections
            ]
            declared = self.integer("DeviceInfo", f"NrOf{kind}PDO", 0, 512)
            if declared is not None and declared != len(comms):
                self.fail("DeviceInfo", f"NrOf{kind}PDO={declared} but {len(comms)} {kind}PDOs")
            for comm in comms:
                mapping = first_map + comm - first_comm
                if f"{mapping:04X}" not in self.sections:
                    self.fail(f"{comm:04X}", f"no mapping object 0x{mapping:04X}")
                else:
                    self.mapping(f"{mapping:04X}")

    def mapping(self, name: str) -> None:
        count = _int(self.get(f"{name}sub0", "DefaultValue") or "0")
        total = 0
        for sub in range(1, count + 1):
            entry = self.get(f"{name}sub{sub:X}", "DefaultValue")
            if entry is None:
                self.fail(name, f"mapped object {sub} missing")
                continue
            value = _int(entry)
            index, subindex, bits = value >> 16, (value >> 8) & 0xFF, value & 0xFF
            target = f"{index:04X}" + (f"sub{subindex:X}" if subindex else "")
            data_type = self.get(target, "DataType")
            if data_type is None:
                self.fail(name, f"maps 0x{index:04X}:{subindex} which does not exist")
                continue
            if self.get(target, "PDOMapping") != "1":
                self.fail(name, f"maps 0x{index:04X}:{subindex} which has PDOMapping=0")
            if DATA_TYPES.get(_int(data_type), ("", -1))[1] != bits:
                self.fail(name, f"maps 0x{index:04X}:{subindex} with {bits} bits, not its length")
            total += bits
        if total > 64:
            self.fail(name, f"maps {total} bits, more than 64")


def check_eds(path: str | Path) -> list[str]:
    """The CiA 306 problems of the EDS at ``path`` (empty when it is clean)."""
    text = Path(path).read_text(encoding="ascii")
    try:
        return _Checker(text).run()
    except configparser.Error as error:
        return [f"not an EDS (INI syntax): {error}"]


def main(argv: list[str] | None = None) -> int:
    """Check each EDS given; print the problems; 1 if any."""
    problems = [f"{path}: {p}" for path in (argv or sys.argv[1:]) for p in check_eds(path)]
    print("\n".join(problems) if problems else "no problems")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
