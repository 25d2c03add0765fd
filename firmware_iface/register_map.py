"""The register map of docs/registers.md, loaded from ``registers.yaml``.

One source for the driver and the simulated units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntFlag
from functools import cache
from pathlib import Path

import yaml

from xmalign.errors import FormatError

REGISTER_MAP_PATH = Path(__file__).with_name("registers.yaml")


@dataclass(frozen=True)
class Register:
    """One register: 0-based ``address``, ``type`` (uint16, uint32, int32) and ``access``."""

    name: str
    address: int
    type: str
    access: str

    @property
    def width(self) -> int:
        """Number of 16-bit registers the value occupies."""
        return 1 if self.type == "uint16" else 2


@dataclass(frozen=True)
class RegisterMap:
    """The register map, bit meanings and watchdog timing of registers.yaml."""

    device: dict[str, Register]
    axis_stride: int
    axis_registers: dict[str, Register]
    fault_codes: dict[int, str]
    heartbeat_period_s: float
    watchdog_timeout_s: float
    quick_stop_start_s: float
    quick_stop_rad_s2: float
    device_types: dict[str, int]

    def axis(self, n: int, name: str) -> Register:
        """Register ``name`` of axis ``n`` (1-based), with its absolute address."""
        reg = self.axis_registers[name]
        return Register(f"axis{n}.{name}", self.axis_stride * n + reg.address, reg.type, reg.access)

    def fault_text(self, code: int) -> str:
        return self.fault_codes.get(code, f"unknown fault code {code}")


@cache
def load_register_map(path: Path = REGISTER_MAP_PATH) -> RegisterMap:
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    block = data["axis_block"]
    return RegisterMap(
        device={
            k: Register(k, v["address"], v["type"], v["access"]) for k, v in data["device"].items()
        },
        axis_stride=block["base_stride"],
        axis_registers={
            k: Register(k, v["offset"], v["type"], v["access"])
            for k, v in block["registers"].items()
        },
        fault_codes={int(k): v for k, v in data["fault_codes"].items()},
        heartbeat_period_s=data["watchdog"]["heartbeat_period_ms"] / 1000.0,
        watchdog_timeout_s=data["watchdog"]["timeout_ms"] / 1000.0,
        quick_stop_start_s=data["watchdog"]["quick_stop_start_ms"] / 1000.0,
        quick_stop_rad_s2=math.radians(data["watchdog"]["quick_stop_deg_s2"]),
        device_types=data["device_types"],
    )


class Control(IntFlag):
    """Bits of an axis's control register (registers.yaml ``control_bits``)."""

    ENABLE = 1 << 0
    UNLOCK = 1 << 1
    START = 1 << 2
    STOP = 1 << 3
    FAULT_RESET = 1 << 4
    HOME = 1 << 5
    TRACK = 1 << 6


class Status(IntFlag):
    """Bits of an axis's status register (registers.yaml ``status_bits``)."""

    ENABLED = 1 << 0
    IN_POSITION = 1 << 1
    MOVING = 1 << 2
    FAULT = 1 << 3
    LOCKED = 1 << 4
    HOMED = 1 << 5
    AT_LIMIT = 1 << 6
    TRACKING = 1 << 7


def check_bits(path: Path = REGISTER_MAP_PATH) -> None:
    """FormatError unless the bits of ``path`` are those of :class:`Control` and :class:`Status`.

    The classes are static so that type checkers know them; the YAML stays the reference.
    """
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    for flags, key in ((Control, "control_bits"), (Status, "status_bits")):
        declared = {name.upper(): 1 << bit for name, bit in data[key].items()}
        if declared != {flag.name: flag.value for flag in flags}:
            raise FormatError(
                f"{path}: {key} differ from firmware_iface.register_map.{flags.__name__}"
            )


check_bits()
