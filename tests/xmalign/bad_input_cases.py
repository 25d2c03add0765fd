"""The table of bad inputs and careless commands of tests/xmalign/test_bad_input.py.

Each :class:`Case` starts from a folder holding a copy of every valid example
file (``examples/``) plus an empty-but-valid measurement CSV, damages one of
them, runs one ``xmalign`` command in-process in that folder and expects one
line on stderr naming the file (or option) and the key or line, exit code 2
(130 for Ctrl-C), no traceback, and every file that was there before
byte-identical afterwards. ``run_case`` returns what happened so that
``tests/benchmarks/bench_bad_input.py`` can tally the same table.

Not here: the measurement CSV and ``run``'s resume semantics (their own tests).
"""

from __future__ import annotations

import errno
import hashlib
import io
import json
import os
import shutil
import socket
import stat
import sys
import traceback
from collections.abc import Callable
from contextlib import redirect_stderr, redirect_stdout
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = (
    "fyxz.yaml",
    "units.yaml",
    "session.json",
    "pose.json",
    "plan.json",
    "errors.csv",
    "tracker.csv",
    "tracer.csv",
    "spatial-analyzer.txt",
)
MEASUREMENTS_HEADER = (
    "line,run,direction,index,target_mm,x_mm,y_mm,z_mm,linear_um,straightness_v_um,"
    "straightness_w_um,angle_u_urad,angle_v_urad,angle_w_urad\n"
)

#: One command per file kind; the damaged file is the one it reads first.
COMMAND = {
    "fyxz.yaml": ("comp", "--errors", "errors.csv", "--out", "comp", "--machine", "fyxz.yaml"),
    "units.yaml": ("align", "--live", "--config", "units.yaml", "--timeout", "0.1"),
    "session.json": ("identify", "--input", "session.json", "--out", "pose-new.json"),
    "pose.json": ("program", "--pose", "pose.json", "--out", "run.mpf"),
    "plan.json": ("post", "--plan", "plan.json", "--data", "m.csv", "--out", "errors-new.csv"),
    "errors.csv": ("comp", "--errors", "errors.csv", "--out", "comp"),
    "tracker.csv": ("post", "--tracker", "tracker.csv", "--out", "errors-new.csv"),
    "tracer.csv": ("post", "--tracer", "tracer.csv", "--out", "errors-new.csv"),
    "spatial-analyzer.txt": (
        "import",
        "--spatial-analyzer",
        "spatial-analyzer.txt",
        "--points",
        "points.csv",
        "--out",
        "tracker-new.csv",
    ),
}

Damage = Callable[[Path], None]
Patch = Callable[[pytest.MonkeyPatch], None]


@dataclass(frozen=True)
class Case:
    id: str
    argv: tuple[str, ...]
    fragments: tuple[str, ...]
    damage: Damage | None = None
    patch: Patch | None = None
    code: int = 2


@dataclass
class Outcome:
    """What one case did: exit code, stderr lines, a traceback, files changed."""

    code: int | None
    stderr_lines: list[str]
    traceback: str = ""
    damaged: list[str] = field(default_factory=list)
    leftovers: list[str] = field(default_factory=list)


# -- damage helpers -----------------------------------------------------------------------


def write(name: str, content: str | bytes) -> Damage:
    def apply(folder: Path) -> None:
        path = folder / name
        path.parent.mkdir(exist_ok=True)
        path.unlink(missing_ok=True)
        if isinstance(content, bytes):
            path.write_bytes(content)
        else:
            path.write_text(content, encoding="utf-8")

    return apply


def replace(name: str, old: str, new: str) -> Damage:
    def apply(folder: Path) -> None:
        path = folder / name
        text = path.read_text(encoding="utf-8")
        assert old in text, f"{old!r} not in {name}"
        path.write_text(text.replace(old, new, 1), encoding="utf-8")

    return apply


def edit_json(name: str, change: Callable[[dict], Any]) -> Damage:
    def apply(folder: Path) -> None:
        path = folder / name
        data = json.loads(path.read_text(encoding="utf-8"))
        change(data)
        path.write_text(json.dumps(data, indent=1), encoding="utf-8")  # NaN written as NaN

    return apply


def append(name: str, text: str) -> Damage:
    def apply(folder: Path) -> None:
        with (folder / name).open("a", encoding="utf-8") as handle:
            handle.write(text)

    return apply


def each(*damages: Damage) -> Damage:
    """All of ``damages``, in order."""

    def apply(folder: Path) -> None:
        for damage in damages:
            damage(folder)

    return apply


def remove(name: str) -> Damage:
    return lambda folder: (folder / name).unlink()


def folder_instead(name: str) -> Damage:
    def apply(folder: Path) -> None:
        (folder / name).unlink()
        (folder / name).mkdir()

    return apply


def bad_byte(name: str) -> Damage:
    def apply(folder: Path) -> None:
        path = folder / name
        data = bytearray(path.read_bytes())
        data[len(data) // 2] = 0xFF
        path.write_bytes(bytes(data))

    return apply


def truncated(name: str) -> Damage:
    def apply(folder: Path) -> None:
        path = folder / name
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])

    return apply


def sets(*path: str | int, value: Any) -> Callable[[dict], None]:
    """A change of a JSON document: set the value at ``path``."""

    def change(data: dict) -> None:
        target: Any = data
        for part in path[:-1]:
            target = target[part]
        target[path[-1]] = value

    return change


def both(*damages: Damage) -> Damage:
    def apply(folder: Path) -> None:
        for damage in damages:
            damage(folder)

    return apply


# -- patches: what a test machine cannot do for real (root ignores permissions) ----------


def _raise(error: BaseException) -> Callable[..., Any]:
    def fail(*args: object, **kwargs: object) -> Any:
        raise error

    return fail


def read_only_folder(monkeypatch: pytest.MonkeyPatch) -> None:
    import xmalign.formats.common as common

    error = PermissionError(errno.EACCES, "Permission denied")
    monkeypatch.setattr(common.tempfile, "mkstemp", _raise(error))


def full_disk(monkeypatch: pytest.MonkeyPatch) -> None:
    import xmalign.formats.common as common

    monkeypatch.setattr(common.os, "fsync", _raise(OSError(errno.ENOSPC, "No space left")))


def unreadable(name: str) -> Patch:
    """Reading ``name`` fails as without read permission (root can read anything)."""
    read_bytes = Path.read_bytes

    def guarded(path: Path) -> bytes:
        if path.name == name:
            raise PermissionError(errno.EACCES, "Permission denied", str(path))
        return read_bytes(path)

    return lambda monkeypatch: monkeypatch.setattr(Path, "read_bytes", guarded)


def ctrl_c_in(module: str, name: str, message: str = "") -> Patch:
    def patch(monkeypatch: pytest.MonkeyPatch) -> None:
        error = KeyboardInterrupt(message) if message else KeyboardInterrupt()
        monkeypatch.setattr(f"{module}.{name}", _raise(error))

    return patch


def os_error_in(module: str, name: str, filename: str) -> Patch:
    def patch(monkeypatch: pytest.MonkeyPatch) -> None:
        error = OSError(errno.EIO, "Input/output error", filename)
        monkeypatch.setattr(f"{module}.{name}", _raise(error))

    return patch


# -- the table ----------------------------------------------------------------------------


def _generic_cases() -> list[Case]:
    """The same six damages to every file kind."""
    cases = []
    for name, argv in COMMAND.items():
        cases += [
            Case(f"{name}-missing", argv, (name, "no such file"), remove(name)),
            Case(f"{name}-folder", argv, (name, "is a folder"), folder_instead(name)),
            Case(f"{name}-not-utf8", argv, (name, "not UTF-8", "line"), bad_byte(name)),
            Case(f"{name}-empty", argv, (name,), write(name, "")),
            Case(f"{name}-truncated", argv, (name,), truncated(name)),
            Case(f"{name}-binary", argv, (name,), write(name, bytes(range(256)) * 4)),
            Case(
                f"{name}-no-permission", argv, (name, "permission denied"), patch=unreadable(name)
            ),
        ]
    return cases


M = "fyxz.yaml"
MACHINE = COMMAND[M]
_CNC = "  acceleration_mm_s2: 1000"
_MACHINE_CASES = [
    ("nan-travel", replace(M, "X: [0, 2000]", "X: [0, .nan]"), "travel_mm.X.1"),
    ("inf-travel", replace(M, "X: [0, 2000]", "X: [0, .inf]"), "travel_mm.X.1"),
    ("1e12-travel", replace(M, "X: [0, 2000]", "X: [0, 1.0e12]"), "travel_mm.X.1"),
    ("101m-travel", replace(M, "X: [0, 2000]", "X: [-60000, 60000]"), "travel_mm"),
    ("reversed-travel", replace(M, "X: [0, 2000]", "X: [2000, 0]"), "travel_mm"),
    ("axis-missing", replace(M, "  Z: [-500, 0]\n", ""), "travel_mm"),
    ("duplicate-key", append(M, "chain: FXYZ\n"), "'chain' given twice"),
    ("duplicate-nested-key", replace(M, "  Y: [0, 1500]", "  Y: [0, 1500]\n  X: [0, 9]"), "'X'"),
    ("unknown-key", append(M, "spindel_angle_deg: 0\n"), "spindel_angle_deg"),
    ("missing-chain", replace(M, "chain: FYXZ\n", ""), "key 'chain': missing"),
    ("bad-chain", replace(M, "chain: FYXZ", "chain: FXXZ"), "key 'chain'"),
    ("spindle-1e6", replace(M, "spindle_angle_deg: 0", "spindle_angle_deg: 1.0e6"), "spindle"),
    ("spindle-string", replace(M, "spindle_angle_deg: 0", "spindle_angle_deg: ninety"), "spindle"),
    ("negative-feed", replace(M, "measure: 2000", "measure: -2000"), "feed_mm_min.measure"),
    ("inf-feed", replace(M, "rapid: 8000", "rapid: .inf"), "feed_mm_min.rapid"),
    ("offset-two", replace(M, "[0, 0, -180]", "[0, -180]"), "receiver_offset_mm"),
    ("offset-nan", replace(M, "[0, 0, -180]", "[0, .nan, -180]"), "receiver_offset_mm.1"),
    ("launch-1e12", replace(M, "[100, 100, -680]", "[100, 1.0e12, -680]"), "launch_unit"),
    (
        "thermal-1e3",
        replace(M, "expansion_ppm_per_k: 11.5", "expansion_ppm_per_k: 1000"),
        "thermal.expansion",
    ),
    (
        "thermal-nan",
        replace(M, "expansion_ppm_per_k: 11.5", "expansion_ppm_per_k: .nan"),
        "thermal.expansion",
    ),
    ("thermal-unknown", replace(M, "expansion_ppm_per_k: 11.5", "alpha: 11.5"), "thermal.alpha"),
    (
        "thermal-drift-negative",
        replace(M, "drift_limit_um: 2.0", "drift_limit_um: -2.0"),
        "thermal.drift_limit_um",
    ),
    ("range-negative", replace(M, "angle_range_urad: 500", "angle_range_urad: -500"), "angle_r"),
    ("range-inf", replace(M, "max_range_mm: 4000", "max_range_mm: .inf"), "max_range_mm"),
    ("controller", replace(M, "controller: sinumerik", "controller: haas"), "controller"),
    ("syntax", append(M, "name: [unclosed\n"), "line"),
    ("a-list", write(M, "- a\n- b\n"), "mapping"),
    ("tab-indent", replace(M, "  X: [0, 2000]", "\tX: [0, 2000]"), "line"),
    ("bad-date", append(M, "built: 2024-13-45\n"), M),
    # the controller model (docs/controllers.md)
    ("series-of-another-family", replace(M, _CNC, _CNC + "\n  series: 30i"), "cnc.series"),
    ("reference-return-up", replace(M, _CNC, _CNC + "\n  reference_return: {X: up}"), "X"),
    ("backlash-negative", replace(M, _CNC, _CNC + "\n  backlash_um: {Y: -3}"), "backlash_um.Y"),
    (
        "itnc-530",
        each(
            replace(M, "controller: sinumerik", "controller: heidenhain"),
            replace(M, _CNC, _CNC + "\n  series: iTNC 530"),
        ),
        "iTNC 530",
    ),
    (
        "reference-inside-without-return",
        replace(M, _CNC, _CNC + "\n  reference_mm: [1000, 0, 0]"),
        "cnc.reference_return.X",
    ),
]

U = "units.yaml"
UNITS = COMMAND[U]
_UNITS_CASES = [
    ("duplicate-key", append(U, "launch: {transport: modbus-tcp, host: x}\n"), "given twice"),
    ("unknown-transport", replace(U, "transport: modbus-tcp", "transport: usb"), "launch"),
    ("port-70000", replace(U, "port: 502", "port: 70000"), "port"),
    ("timeout-inf", replace(U, "io_s: 1.0", "io_s: .inf"), "timeouts.io_s"),
    ("timeout-negative", replace(U, "move_s: 30.0", "move_s: -1"), "timeouts.move_s"),
    ("timeout-a-day", replace(U, "move_s: 30.0", "move_s: 86400"), "timeouts.move_s"),
    ("no-format", replace(U, "format: xmalign.units/1", "formt: xmalign.units/1"), "format"),
    ("format-2", replace(U, "format: xmalign.units/1", "format: xmalign.units/2"), "newer xmalign"),
    ("rate-nan", replace(U, "rate_hz: 50", "rate_hz: .nan"), "rate_hz"),
    ("mtconnect-missing", replace(U, "source: prompt", "source: mtconnect"), "mtconnect"),
    (
        "mtconnect-ftp",
        replace(U, "source: prompt", "source: mtconnect\n  mtconnect: {url: 'ftp://a'}"),
        "mtconnect.url",
    ),
    ("linuxcnc-missing", replace(U, "source: prompt", "source: linuxcnc"), "'linuxcnc' is req"),
    (
        "linuxcnc-no-program",
        replace(U, "source: prompt", "source: linuxcnc\n  linuxcnc: {joints: 3}"),
        "linuxcnc.program",
    ),
    (
        "linuxcnc-host",
        replace(U, "source: prompt", "source: linuxcnc\n  linuxcnc: {program: p.ngc, host: cnc}"),
        "linuxcnc.host",
    ),
    (
        "linuxcnc-joints-0",
        replace(U, "source: prompt", "source: linuxcnc\n  linuxcnc: {program: p.ngc, joints: 0}"),
        "linuxcnc.joints",
    ),
    *(
        (
            f"secret-{source}-{key}-{name}",
            replace(
                U, "source: prompt", f"source: {source}\n  {source}: {{{base}, {key}: {value}}}"
            ),
            f"{source}.{key}",
        )
        for source, base in [
            ("linuxcncrsh", "host: cnc, program: p.ngc"),
            ("sinumerik", "endpoint: 'opc.tcp://a:4840', user: u"),
        ]
        for key in (
            ["connect_password", "enable_password"] if source == "linuxcncrsh" else ["password"]
        )
        for name, value in [("yes", "yes"), ("decimal", "47.11"), ("list", "[47, 11]")]
    ),
    (
        "linuxcncrsh-password-with-a-space",
        replace(
            U,
            "source: prompt",
            "source: linuxcncrsh\n  linuxcncrsh: {host: cnc, program: p.ngc,"
            " enable_password: 'top secret'}",
        ),
        "linuxcncrsh.enable_password",
    ),
    (
        "sinumerik-policy-no-certificate",
        replace(
            U,
            "source: prompt",
            "source: sinumerik\n  sinumerik: {endpoint: 'opc.tcp://a:4840', "
            "security_policy: Basic256Sha256}",
        ),
        "certificate",
    ),
    (
        "mtconnect-program-name-blank",
        replace(
            U,
            "source: prompt",
            "source: mtconnect\n  mtconnect: {url: 'http://a', program_name: ' '}",
        ),
        "mtconnect.program_name",
    ),
    *(
        (
            f"sinumerik-program-{name}",
            replace(
                U,
                "source: prompt",
                f"source: sinumerik\n  sinumerik: {{endpoint: 'opc.tcp://a:4840', {value}}}",
            ),
            key,
        )
        for name, value, key in [
            ("nc-notation", "program: /_N_MPF_DIR/_N_RUN_MPF", "sinumerik.program"),
            (
                "subprogram",
                "program: 'Sinumerik/FileSystem/Sub Program/RUN.SPF'",
                "sinumerik.program",
            ),
            (
                "two-extensions",
                "program: 'Sinumerik/FileSystem/Part Program/RUN.MPF.MPF'",
                "program",
            ),
            ("copy-without-program", "copy_program: true", "copy_program needs 'program'"),
            (
                "copy-yes-please",
                "program: 'Sinumerik/FileSystem/Part Program/R.MPF', copy_program: please",
                "copy_program",
            ),
            ("name-empty", "program_name: ''", "sinumerik.program_name"),
        ]
    ),
]

S = "session.json"
SESSION = COMMAND[S]
_SESSION_CASES = [
    ("nan", edit_json(S, sets("alignments", 0, "machine_mm", 0, value=float("nan"))), "machine_mm"),
    (
        "infinity",
        edit_json(S, sets("alignments", 1, "launch_deg", 0, value=float("inf"))),
        "launch",
    ),
    ("-infinity", edit_json(S, sets("spindle_angle_deg", value=float("-inf"))), "spindle_angle"),
    ("1e400", replace(S, '"spindle_angle_deg": 0.0', '"spindle_angle_deg": 1e400'), "spindle"),
    ("angle-1e9", edit_json(S, sets("alignments", 0, "launch_deg", 1, value=1e9)), "launch_deg"),
    ("position-1e12", edit_json(S, sets("alignments", 0, "machine_mm", 2, value=1e12)), "machine"),
    ("distance-negative", edit_json(S, sets("alignments", 0, "distance_mm", value=-5)), "distance"),
    (
        "straightness-1e6",
        edit_json(S, sets("alignments", 0, "straightness_um", value=[1e6, 0])),
        "str",
    ),
    (
        "duplicate-key",
        replace(
            S, '"spindle_angle_deg": 0.0,', '"spindle_angle_deg": 0.0, "spindle_angle_deg": 1,'
        ),
        "given twice",
    ),  # noqa: E501
    ("no-format", edit_json(S, lambda d: d.pop("format")), "key 'format'"),
    ("foreign-format", edit_json(S, sets("format", value="xmalign.plan/1")), "format"),
    ("offset-two", edit_json(S, sets("receiver_offset_mm", value=[0, 0])), "receiver_offset_mm"),
    ("alignments-dict", edit_json(S, sets("alignments", value={"a": 1})), "alignments"),
    ("top-level-list", write(S, "[1, 2, 3]"), "JSON object"),
    ("deep-nesting", write(S, "[" * 100_000 + "]" * 100_000), S),
    (
        "huge-integer",
        write(S, '{"format": "xmalign.identify-session/1", "x": ' + "9" * 5000 + "}"),
        S,
    ),  # noqa: E501
    ("string-angle", edit_json(S, sets("alignments", 0, "launch_deg", value=["a", "b"])), "launch"),
]

P = "pose.json"
POSE = COMMAND[P]


def _asymmetric(data: dict) -> None:
    data["covariance"][0][1] = 1.0


def _not_psd(data: dict) -> None:
    data["covariance"] = [[1, 2, 0, 0], [2, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1e-9]]


_POSE_CASES = [
    ("gamma-infinity", replace(P, '"gamma_deg": -67', '"gamma_deg": Infinity, "x": -67'), "gamma"),
    ("gamma-nan", edit_json(P, sets("gamma_deg", value=float("nan"))), "gamma_deg"),
    ("position-nan", edit_json(P, sets("position_mm", 1, value=float("nan"))), "position_mm.1"),
    ("position-1e12", edit_json(P, sets("position_mm", 0, value=1e12)), "position_mm.0"),
    ("asymmetric", edit_json(P, _asymmetric), "covariance"),
    ("negative-variance", edit_json(P, sets("covariance", 3, 3, value=-1e-9)), "covariance"),
    ("not-psd", edit_json(P, _not_psd), "positive semi-definite"),
    ("covariance-3x3", edit_json(P, sets("covariance", value=[[1, 0, 0]] * 3)), "covariance"),
    ("unknown-offset", edit_json(P, sets("encoder_offsets_deg", "c9", value=1)), "c9"),
    ("offset-nan", edit_json(P, sets("encoder_offsets_deg", "c2", value=float("nan"))), "c2"),
    ("residual-negative", edit_json(P, sets("residual_rms_um", value=-3)), "residual_rms_um"),
    (
        "duplicate-key",
        replace(P, '"method": "joint",', '"method": "joint", "method": "x",'),
        "method",
    ),
    ("format-9", edit_json(P, sets("format", value="xmalign.launch-pose/9")), "reads up to /1"),
]

L = "plan.json"

#: ``run`` on a LinuxCNC xmalign runs its program on: refused before any device is opened.
_CONTROLLED_RUN = ("run", "--config", U, "--plan", L, "--out", "new.csv")


def _controlled_units(program: str) -> Damage:
    return replace(
        U,
        "source: prompt",
        f"source: linuxcncrsh\n  linuxcncrsh: {{host: cnc, program: {program}}}",
    )


PLAN = COMMAND[L]


def _frame(data: dict, u: list, v: list, w: list) -> None:
    data["lines"][0]["frame"] = {"u": u, "v": v, "w": w}


def _line(key: str, value: Any, index: int = 0) -> Callable[[dict], None]:
    return sets("lines", index, key, value=value)


_PLAN_CASES = [
    ("frame-skew", edit_json(L, lambda d: _frame(d, [1, 0, 0], [0.1, 1, 0], [0, 0, 1])), "frame"),
    ("frame-long", edit_json(L, lambda d: _frame(d, [2, 0, 0], [0, 1, 0], [0, 0, 1])), "frame"),
    ("frame-left", edit_json(L, lambda d: _frame(d, [1, 0, 0], [0, 1, 0], [0, 0, -1])), "left"),
    (
        "frame-nan",
        edit_json(L, lambda d: _frame(d, [1, 0, 0], [0, 1, 0], [0, 0, float("nan")])),
        "frame",
    ),  # noqa: E501
    ("duplicate-id", edit_json(L, _line("id", "X", 1)), "'X' is given twice"),
    ("empty-id", edit_json(L, _line("id", "")), "lines.0.id"),
    ("targets-decreasing", edit_json(L, _line("targets_mm", [0, 200, 100])), "increase"),
    ("targets-beyond", edit_json(L, _line("targets_mm", [0, 100, 99999])), "leave the line"),
    ("targets-nan", edit_json(L, _line("targets_mm", [0, float("nan")])), "targets_mm"),
    ("start-1e12", edit_json(L, sets("lines", 0, "start_mm", 0, value=1e12)), "start_mm.0"),
    (
        "launch-infinity",
        edit_json(L, sets("lines", 2, "launch_deg", 1, value=float("inf"))),
        "lines.2",
    ),  # noqa: E501
    ("runs-0", edit_json(L, _line("runs", 0)), "runs"),
    ("runs-1e9", edit_json(L, _line("runs", 10**9)), "runs"),
    ("dwell-negative", edit_json(L, _line("dwell_s", -1)), "dwell_s"),
    ("no-lines", edit_json(L, sets("lines", value=[])), "lines"),
    ("lines-missing", edit_json(L, lambda d: d.pop("lines")), "key 'lines': missing"),
    ("extra-nan", edit_json(L, _line("margin_um", float("nan"))), "lines.0.margin_um"),
    ("duplicate-key", replace(L, '"machine": ', '"machine": "a", "machine": '), "given twice"),
    ("spindle-string", edit_json(L, sets("spindle_angle_deg", value="0deg")), "spindle"),
]

E = "errors.csv"
ERRORS = COMMAND[E]
_ROW = "EXX,352.220,-8.7083,um,0.7737"
_ERROR_CASES = [
    ("value-nan", replace(E, _ROW, "EXX,352.220,nan,um,0.7737"), "line 3"),
    ("value-inf", replace(E, _ROW, "EXX,352.220,inf,um,0.7737"), "line 3"),
    ("value-minus-inf", replace(E, _ROW, "EXX,352.220,-inf,um,0.7737"), "line 3"),
    ("value-1e12", replace(E, _ROW, "EXX,352.220,1e12,um,0.7737"), "line 3"),
    ("value-2mm", replace(E, _ROW, "EXX,352.220,2000,um,0.7737"), "line 3"),
    ("u95-inf", replace(E, _ROW, "EXX,352.220,-8.7,um,inf"), "line 3"),
    ("u95-negative", replace(E, _ROW, "EXX,352.220,-8.7,um,-0.5"), "line 3: u95"),
    ("rotation-20mrad", replace(E, "EC0Y,,", "EC0Y,,20000,urad,1\nEX,,"), "line"),
    ("squareness-nan", replace(E, "EC0Y,,", "EC0Y,,nan,urad,1\nEX,,"), "line"),
    ("wrong-unit", replace(E, _ROW, "EXX,352.220,-8.7,urad,0.7"), "EXX is in um"),
    ("unknown-name", replace(E, _ROW, "EQQ,352.220,-8.7,um,0.7"), "EQQ"),
    ("duplicate-row", replace(E, _ROW, "EXX,255.586,-8.7,um,0.7"), "repeats line 2"),
    ("duplicate-squareness", append(E, "EC0Y,,1.0,urad,0.1\n"), "repeats line"),
    ("one-point-table", write(E, "name,position_mm,value,unit,u95\nEXX,0,1,um,\n"), "EXX"),
    ("bad-header", replace(E, "name,position_mm", "nam,position_mm"), "line 1"),
    ("four-fields", replace(E, _ROW, "EXX,352.220,-8.7,um"), "line 3: expected 5 fields"),
    ("position-text", replace(E, _ROW, "EXX,abc,-8.7,um,0.7"), "line 3: position_mm"),
    ("position-1e9", replace(E, _ROW, "EXX,1e9,-8.7,um,0.7"), "line 3: position_mm"),
    ("squareness-position", replace(E, "EC0Y,,", "EC0Y,5,"), "EC0Y"),
    ("nul-byte", replace(E, _ROW, "EXX,352.220,-8.7\x00,um,0.7"), E),
]


T, R = "tracker.csv", "tracer.csv"
TRACKER, TRACER = COMMAND[T], COMMAND[R]


def _with_column(name: str, column: str, first: str) -> Damage:
    """A column added to every row of an instrument file, ``first`` in the first row only."""

    def apply(folder: Path) -> None:
        path = folder / name
        lines = path.read_text(encoding="utf-8").splitlines()
        header = next(i for i, line in enumerate(lines) if not line.startswith("#"))
        lines[header] += f",{column}"
        lines[header + 1] += f",{first}"
        lines[header + 2 :] = [line + "," for line in lines[header + 2 :]]
        path.write_text("\n".join(lines) + "\n", encoding="utf-8")

    return apply


_TRACKER_CASES = [
    ("unknown-smr", _with_column(T, "smr", "B"), "line 4: smr 'B' is not a key"),
    ("material-300", _with_column(T, "material_c", "300"), "material_c 300 lies outside"),
    ("wrong-format", replace(T, "tracker-points/1", "tracker-points/2"), "line 1"),
    ("nan-point", replace(T, "\nT1,0,0,0.0,", "\nT1,0,0,nan,"), "not a finite number"),
    ("no-index-no-path", replace(T, "\nT1,0,0,", "\nT1,0,,"), "on the fly"),
    ("repeated", replace(T, "\nT1,1,0,", "\nT1,0,0,"), "repeats the reading"),
    ("missing-column", replace(T, ",tz_mm", ""), "lacks column tz_mm"),
    (
        "two-points",
        write(
            T,
            "# xmalign tracker-points/1\nstation,run,index,x_mm,y_mm,z_mm,"
            "tx_mm,ty_mm,tz_mm\nT1,0,0,0,0,0,1,2,3\nT1,0,1,9,0,0,10,2,3\n",
        ),
        "X axis stood at 2",
    ),
]
_TRACER_CASES = [
    ("unknown-smr", _with_column(R, "smr", "B"), "line 8: smr 'B' is not a key"),
    ("material-300", _with_column(R, "material_c", "300"), "material_c 300 lies outside"),
    ("wrong-format", replace(R, "tracer-lengths/1", "tracer-length/1"), "line 1"),
    ("bad-guess", replace(R, "guess_mm=", "guess_mm=x"), "guess_mm"),
    ("inf-length", replace(R, "\nP1,0,0,0.0,", "\nP1,0,0,inf,"), "not a finite number"),
    ("three-places", lambda folder: _keep_tracer_places(folder / R, 3), "3 tracer places"),
]


def _rows(name: str, change: Callable[[dict[str, str], int], None]) -> Damage:
    """Change the data rows of a tracker or tracer CSV: ``change(row, number)`` (0-based)."""

    def apply(folder: Path) -> None:
        path = folder / name
        lines = path.read_text(encoding="utf-8").splitlines()
        head = [line for line in lines if line.startswith("#")]
        header, *rows = [line for line in lines if line and not line.startswith("#")]
        names = header.split(",")
        changed = []
        for number, line in enumerate(rows):
            row = dict(zip(names, line.split(","), strict=True))
            change(row, number)
            changed.append(row)
        columns = list(dict.fromkeys(names + [k for row in changed for k in row]))
        out = [",".join(columns)] + [",".join(row.get(c, "") for c in columns) for row in changed]
        path.write_text("\n".join(head + out) + "\n", encoding="utf-8")

    return apply


def _scaled(columns: tuple[str, ...], factor: float, rows: Callable[[int], bool]) -> Callable:
    def change(row: dict[str, str], number: int) -> None:
        if rows(number):
            for column in columns:
                row[column] = repr(float(row[column]) * factor)

    return change


def _cell(column: str, value: str, at: int | None = 37) -> Callable:
    """``column`` set to ``value`` in row ``at`` (None: every row; a new column elsewhere empty)."""

    def change(row: dict[str, str], number: int) -> None:
        row[column] = value if at is None or number == at else row.get(column, "")

    return change


def _shifted(column: str, by: float, at: int = 40) -> Callable:
    def change(row: dict[str, str], number: int) -> None:
        if number == at:
            row[column] = repr(float(row[column]) + by)

    return change


_ALL, _ODD = (lambda number: True), (lambda number: number % 2 == 1)
_TXYZ = ("tx_mm", "ty_mm", "tz_mm")
_GROSS_TRACKER_CASES = [
    ("in-inches", _rows(T, _scaled(_TXYZ, 1 / 25.4, _ALL)), "the file is in inches"),
    ("in-metres", _rows(T, _scaled(_TXYZ, 1e-3, _ALL)), "the file is in metres"),
    ("half-in-metres", _rows(T, _scaled(_TXYZ, 1e-3, _ODD)), "line 5: this point's"),
    ("point-99999", _rows(T, _cell("tx_mm", "99999")), "line 41: this point's"),
    ("outside-travel", _rows(T, _shifted("x_mm", 3000.0)), "line 44: the commanded point"),
    ("u-radial-1e30", _rows(T, _cell("u_radial_um", "1e30")), "line 41: u_radial_um 1e+30"),
    ("u-radial-0", _rows(T, _cell("u_radial_um", "0")), "line 41: u_radial_um 0 must be > 0"),
    ("u-transverse-negative", _rows(T, _cell("u_transverse_um", "-3")), "must be > 0"),
    ("u-radial-nan", _rows(T, _cell("u_radial_um", "nan")), "line 41: u_radial_um"),
    ("unknown-smr-row", _rows(T, _cell("smr", "Q")), "line 41: smr 'Q'"),
    ("material-999", _rows(T, _cell("material_c", "999")), "line 41: material_c 999"),
]
_GROSS_TRACER_CASES = [
    ("in-inches", _rows(R, _scaled(("length_mm",), 1 / 25.4, _ALL)), "in inches, not in mm"),
    ("in-metres", _rows(R, _scaled(("length_mm",), 1e-3, _ALL)), "in metres, not in mm"),
    ("half-in-metres", _rows(R, _scaled(("length_mm",), 1e-3, _ODD)), "line 9: this length"),
    ("length-0", _rows(R, _cell("length_mm", "0")), "line 45: length_mm 0"),
    ("length-99999", _rows(R, _cell("length_mm", "99999")), "line 45: this length"),
    ("outside-travel", _rows(R, _shifted("y_mm", 3000.0)), "line 48: the commanded point"),
]
_TRACKER_CASES += _GROSS_TRACKER_CASES
_TRACER_CASES += _GROSS_TRACER_CASES


def _same_file_cases() -> list[Case]:
    """The same readings twice: the same file, a link to it, a copy (by content)."""
    cases = []
    for kind, name in (("tracker", T), ("tracer", R)):
        option = f"--{kind}"
        for how, damage, fragment in (
            ("twice", None, "is the same file as"),
            ("link", lambda f, n=name: (f / "again.csv").symlink_to(n), "is the same file as"),
            ("copy", lambda f, n=name: shutil.copy(f / n, f / "again.csv"), "the same readings"),
        ):
            again = name if damage is None else "again.csv"
            argv = ("post", option, name, option, again, "--out", "errors-new.csv")
            cases.append(Case(f"{name}-{how}", argv, (again, fragment, name), damage))
    return cases


def _export_lines(change: Callable[[list[str]], list[str]]) -> Damage:
    """Change every point line of the SpatialAnalyzer export (fields split on spaces)."""

    def apply(folder: Path) -> None:
        path = folder / "spatial-analyzer.txt"
        lines = path.read_text(encoding="utf-8").splitlines()
        changed = [x if x.startswith("//") else " ".join(change(x.split())) for x in lines]
        path.write_text("\n".join(changed) + "\n", encoding="utf-8")

    return apply


_SA = "spatial-analyzer.txt"
_IMPORT_CASES = [
    Case(
        "import-inches-as-mm",
        COMMAND[_SA],
        (_SA, "line 3", "in inches", "--units in"),
        _export_lines(lambda f: [*f[:3], *(str(float(v) / 25.4) for v in f[3:])]),
    ),
    Case(
        "import-names-shifted",
        COMMAND[_SA],
        (_SA, "line 3", "names shifted"),
        _export_lines(lambda f: [*f[:2], str(int(f[2]) + 1), *f[3:]]),
    ),
    Case("import-units-yd", (*COMMAND[_SA], "--units", "yd"), ("--units", "yd")),
    Case("import-naming-bad", (*COMMAND[_SA], "--naming", "x"), ("--naming", "'x'")),
    Case(
        "program-tracker-simultaneous",
        ("program", "--instrument", "tracker", "--simultaneous"),
        ("--simultaneous is for --instrument tracer",),
    ),
    Case(
        "dry-run-tracker-simultaneous",
        ("dry-run", "--instrument", "tracker", "--simultaneous", "--out", "dry"),
        ("--simultaneous is for --instrument tracer",),
    ),
    Case(
        "import-both-exports",
        (*COMMAND[_SA], "--name-xyz", _SA),
        ("--spatial-analyzer", "--name-xyz"),
    ),
]


STREAM = "stream.csv"
_STREAM = (
    "# xmalign tracker-stream/1\nstation,run,time_s,tx_mm,ty_mm,tz_mm\n"
    "T1,0,0.0,1,2,3\nT1,0,0.01,1,2,3\nT1,0,0.02,1,2,3\n"
)
_IMPORT_STREAM = ("import", "--tracker-stream", STREAM, "--points", "points.csv")
_STREAM_CASES = [
    Case(
        "stream-wrong-format",
        (*_IMPORT_STREAM, "--out", "t.csv"),
        (STREAM, "line 1", "tracker-stream/1"),
        write(STREAM, _STREAM.replace("stream/1", "stream/2")),
    ),
    Case(
        "stream-not-a-number",
        (*_IMPORT_STREAM, "--out", "t.csv"),
        (STREAM, "line 4", "ty_mm"),
        write(STREAM, _STREAM.replace("0.01,1,2", "0.01,1,x")),
    ),
    Case(
        "stream-missing-column",
        (*_IMPORT_STREAM, "--out", "t.csv"),
        (STREAM, "line 2", "lacks column tz_mm"),
        write(STREAM, _STREAM.replace(",tz_mm", "")),
    ),
    Case(
        "stream-points-without-paths",
        (*_IMPORT_STREAM, "--out", "t.csv"),
        ("points.csv", "no paths"),
        write(STREAM, _STREAM),
    ),
    Case(
        "stream-units-not-used",
        (*_IMPORT_STREAM, "--units", "in", "--out", "t.csv"),
        ("--units is not used with --tracker-stream",),
        write(STREAM, _STREAM),
    ),
    Case(
        "stream-out-is-the-points",
        (*_IMPORT_STREAM, "--out", "points.csv"),
        ("points.csv", "--out", "--points"),
        write(STREAM, _STREAM),
    ),
    Case(
        "stream-and-export",
        (*_IMPORT_STREAM, "--spatial-analyzer", "spatial-analyzer.txt", "--out", "t.csv"),
        ("--spatial-analyzer", "--tracker-stream"),
        write(STREAM, _STREAM),
    ),
]


def _keep_tracer_places(path: Path, places: int) -> None:
    keep = tuple(f"P{i + 1}," for i in range(places))
    lines = path.read_text(encoding="utf-8").splitlines(keepends=True)
    path.write_text("".join(x for x in lines if not x.startswith("P") or x.startswith(keep)))


def _kind_cases() -> list[Case]:
    cases = []
    for prefix, argv, table in (
        (M, MACHINE, _MACHINE_CASES),
        (U, UNITS, _UNITS_CASES),
        (S, SESSION, _SESSION_CASES),
        (P, POSE, _POSE_CASES),
        (L, PLAN, _PLAN_CASES),
        (E, ERRORS, _ERROR_CASES),
        (T, TRACKER, _TRACKER_CASES),
        (R, TRACER, _TRACER_CASES),
    ):
        for name, damage, fragment in table:
            cases.append(Case(f"{prefix}-{name}", argv, (prefix, fragment), damage))
    return cases


_CLI_CASES = [
    Case(
        "post-data-as-out",
        ("post", "--plan", L, "--data", "m.csv", "--out", "m.csv"),
        ("m.csv", "--data"),
    ),  # noqa: E501
    Case("post-plan-as-out", ("post", "--plan", L, "--data", "m.csv", "--out", L), (L, "--plan")),
    Case(
        "post-report-plan",
        ("post", "--plan", L, "--data", "m.csv", "--out", "e2.csv", "--report", L),
        (L, "--report"),
    ),  # noqa: E501
    Case(
        "post-out-is-report",
        ("post", "--plan", L, "--data", "m.csv", "--out", "x.csv", "--report", "x.csv"),
        ("x.csv", "--report"),
    ),  # noqa: E501
    Case(
        "post-machine-as-out",
        ("post", "--plan", L, "--data", "m.csv", "--out", M, "--machine", M),
        (M, "--machine"),
    ),  # noqa: E501
    Case(
        "post-out-via-dotdot",
        ("post", "--plan", L, "--data", "m.csv", "--out", "comp/../m.csv"),
        ("m.csv", "--data"),
    ),  # noqa: E501
    Case(
        "post-out-a-link-to-data",
        ("post", "--plan", L, "--data", "m.csv", "--out", "link.csv"),
        ("link.csv", "--data"),
        damage=lambda folder: (folder / "link.csv").symlink_to("m.csv"),
    ),  # noqa: E501
    Case(
        "post-knot-spacing-for-lines",
        ("post", "--plan", L, "--data", "m.csv", "--out", "e2.csv", "--knot-spacing-mm", "50"),
        ("--knot-spacing-mm", "lines set their own"),
    ),
    Case(
        "post-knot-spacing-5",
        ("post", "--tracker", T, "--out", "e2.csv", "--knot-spacing-mm", "5"),
        ("--knot-spacing-mm",),
    ),
    Case("identify-in-as-out", ("identify", "--input", S, "--out", S), (S, "--input")),
    Case("identify-machine-as-out", ("identify", "--input", S, "--out", M, "--machine", M), (M,)),
    Case(
        "identify-session-out-is-out",
        ("identify", "--sim", "--out", "a.json", "--session-out", "a.json"),
        ("a.json",),
    ),  # noqa: E501
    Case("program-pose-as-out", ("program", "--pose", P, "--out", P), (P, "--pose")),
    Case("program-pose-as-plan", ("program", "--pose", P, "--plan-out", P), (P, "--pose")),
    Case("program-out-is-plan", ("program", "--pose", P, "--out", "x", "--plan-out", "x"), ("x",)),
    Case("plan-identify-machine", ("plan-identify", "--machine", M, "--out", M), (M, "--machine")),
    Case("comp-out-a-file", ("comp", "--errors", E, "--out", P), (P, "--out", "folder")),
    Case(
        "comp-volumetric-out-a-file",
        ("comp", "--errors", E, "--out", P, "--controller", "linuxcnc-volumetric", "--ini", M),
        (P, "--out", "folder"),
    ),
    Case("comp-out-the-errors", ("comp", "--errors", E, "--out", E), (E, "--out")),
    Case("mc-out-a-file", ("mc", "--trials", "2", "--out", P), (P, "--out")),
    Case(
        "run-seed", ("run", "--sim", "--plan", L, "--out", "new.csv", "--seed", "-4"), ("--seed",)
    ),  # noqa: E501
    Case(
        "run-plan-missing",
        ("run", "--sim", "--plan", "nope.json", "--out", "new.csv"),
        ("nope.json", "no such file"),
    ),  # noqa: E501
    Case(
        "run-plan-duplicate-ids",
        ("run", "--sim", "--plan", L, "--out", "new.csv"),
        (L, "given twice"),
        damage=edit_json(L, _line("id", "Y", 0)),
    ),  # noqa: E501
    Case(
        "run-plan-gamma-text",
        ("run", "--sim", "--plan", L, "--out", "new.csv"),
        (L, "lines.1.launch_deg.0"),
        damage=edit_json(L, sets("lines", 1, "launch_deg", 0, value="x")),
    ),  # noqa: E501
    Case(
        "run-program-replaces-a-shop-program",  # the controller's folder holds the shop's own
        _CONTROLLED_RUN,
        ("shop.ngc", "not a program xmalign wrote", "not replaced"),
        damage=each(
            write("shop.ngc", "(the shop's own part program)\nG0 X0\nM2\n"),
            _controlled_units("shop.ngc"),
        ),
    ),
    Case("dry-run-seed", ("dry-run", "--seed", "-5", "--out", "dr"), ("--seed", "-5")),
    Case("identify-seed", ("identify", "--sim", "--seed", "-1"), ("--seed",)),
    Case("align-seed", ("align", "--sim", "--seed", "-3"), ("--seed",)),
    Case(
        "identify-live-no-session", ("identify", "--live", "--config", "units.yaml"), ("--session",)
    ),
    Case(
        "identify-uncertainty-negative",
        ("identify", "--input", S, "--encoder-urad", "-1"),
        ("encoder_rad", "must be positive"),
    ),  # noqa: E501
    Case(
        "run-shop-unknown",
        ("run", "--sim", "--plan", L, "--out", "new.csv", "--shop", "nowhere"),
        ("--shop", "'nowhere'", "drifting"),
    ),  # noqa: E501
    Case(
        "comp-ini-for-another-controller",
        ("comp", "--errors", E, "--out", "comp", "--controller", "sinumerik", "--ini", M),
        ("--ini is for the linuxcnc controller", "sinumerik"),
    ),  # noqa: E501
    Case("mc-seed", ("mc", "--seed", "-1", "--out", "mc"), ("--seed",)),
    Case("serve-seed", ("sim", "serve", "--modbus", "127.0.0.1:0", "--seed", "-2"), ("--seed",)),
    Case(
        "serve-can-interface-unknown",
        ("sim", "serve", "--canopen", "x", "--can-interface", "nosuchbus"),
        ("--can-interface nosuchbus", "no CAN interface", "udp_local"),
    ),
    Case(
        "serve-canopen-not-a-group",
        ("sim", "serve", "--canopen", "999.999.1.1"),
        ("--canopen 999.999.1.1", "not an IPv4 multicast group"),
    ),
    # command-line mistakes: one line too, not click's box
    Case("usage-seed-text", ("dry-run", "--seed", "abc"), ("dry-run", "--seed", "--help")),
    Case("usage-missing-value", ("post", "--plan"), ("--plan", "requires an argument")),
    Case("usage-no-such-command", ("frobnicate",), ("No such command 'frobnicate'",)),
    Case("usage-no-such-option", ("sim", "serve", "--foo"), ("sim serve", "--foo")),
    Case("usage-missing-option", ("comp", "--out", "comp"), ("comp", "Missing option '--errors'")),
    Case("usage-alignments-1", ("identify", "--sim", "--alignments", "1"), ("--alignments",)),
    # writing fails: the old output stays as it was
    Case(
        "comp-read-only",
        ("comp", "--errors", E, "--out", "comp", "--force"),
        ("comp", "permission denied"),
        patch=read_only_folder,
    ),  # noqa: E501
    Case(
        "identify-out-read-only",
        ("identify", "--input", S, "--out", "pose-old.json", "--force"),
        ("pose-old.json", "permission denied"),
        patch=read_only_folder,
    ),  # noqa: E501
    Case(
        "plan-identify-read-only",
        ("plan-identify", "--count", "4", "--out", "d.json"),
        ("d.json", "permission denied"),
        patch=read_only_folder,
    ),  # noqa: E501
    Case(
        "comp-full-disk",
        ("comp", "--errors", E, "--out", "comp", "--force"),
        ("comp", "disk full"),
        patch=full_disk,
    ),  # noqa: E501
    Case(
        "identify-full-disk",
        ("identify", "--input", S, "--out", "pose-old.json", "--force"),
        ("pose-old.json", "disk full"),
        patch=full_disk,
    ),  # noqa: E501
    Case(
        "identify-out-a-folder",
        ("identify", "--input", S, "--out", "comp"),
        ("comp", "is a folder"),
    ),  # noqa: E501
    Case("comp-out-under-a-file", ("comp", "--errors", E, "--out", f"{P}/x"), (P,)),
    # Ctrl-C and an unexpected disk error: one line, no traceback
    Case(
        "ctrl-c-comp",
        ERRORS,
        ("stopped by Ctrl-C",),
        patch=ctrl_c_in("xmalign.cli.post", "read_error_tables"),
        code=130,
    ),  # noqa: E501
    Case(
        "ctrl-c-identify",
        SESSION,
        ("stopped by Ctrl-C",),
        patch=ctrl_c_in("xmalign.cli.identify", "solve_step"),
        code=130,
    ),  # noqa: E501
    Case(
        "ctrl-c-message",
        POSE,
        ("stopped: 3 points kept",),
        patch=ctrl_c_in("xmalign.cli.program", "read_pose", "stopped: 3 points kept"),
        code=130,
    ),  # noqa: E501
    Case(
        "os-error-comp",
        ERRORS,
        ("errors.csv", "Input/output error"),
        patch=os_error_in("xmalign.cli.post", "read_error_tables", "errors.csv"),
    ),  # noqa: E501
]


# -- issue 22, careless user: tracebacks, hangs and silent acceptances --------------------


def measured(change: Callable[[list], list] | None = None) -> Damage:
    """m.csv holding a synthetic measurement of plan.json (reference machine), changed."""

    def apply(folder: Path) -> None:
        import numpy as np

        from sim.machine import VirtualMachine
        from sim.synthetic import measure
        from xmalign.formats.measurements import write_measurements
        from xmalign.formats.plan import read_plan
        from xmalign.machine import default_machine_path, load_machine
        from xmalign.rigid_body import Chain

        machine = load_machine(default_machine_path())
        plan = read_plan(folder / L)
        truth = VirtualMachine(machine, seed=4)
        rows = measure(plan, Chain.parse(machine.chain), truth, np.random.default_rng(9))
        (folder / "m.csv").unlink()
        write_measurements(folder / "m.csv", change(rows) if change else rows)

    return apply


# -- outputs that would destroy something (issue 22, "Data damaged" and "Messages") ------
#
# Device nodes, FIFOs and sockets are made in the case's folder, never the real /dev/null.
# Each case also keeps the node what it was (tests/xmalign/test_outputs.py checks that).


def node(name: str, kind: str) -> Damage:
    """A FIFO, a socket, or (root only) a character device like /dev/null or /dev/full."""

    def apply(folder: Path) -> None:
        path = folder / name
        path.parent.mkdir(exist_ok=True)
        path.unlink(missing_ok=True)
        if kind == "fifo":
            os.mkfifo(path)
        elif kind == "socket":
            with socket.socket(socket.AF_UNIX) as server:
                server.bind(str(path))
        else:
            device = {"null": os.makedev(1, 3), "full": os.makedev(1, 7)}[kind]
            os.mknod(path, 0o666 | stat.S_IFCHR, device)

    return apply


def _row_of_z(**changes: Any) -> Callable[[list], list]:
    """Change one row of line Z (run 2, forward, index 3)."""
    from dataclasses import replace as changed

    def change(rows: list) -> list:
        return [changed(r, **changes) if r.key() == ("Z", 2, "+", 3) else r for r in rows]

    return change


def _dead_z(rows: list) -> list:
    from dataclasses import replace as changed

    return [changed(r, channels=0.0 * r.channels) if r.line == "Z" else r for r in rows]


def _x_tables_moved(folder: Path) -> None:
    """The X tables' positions 50 m further: tables of another machine."""
    path = folder / E
    lines = path.read_text(encoding="utf-8").splitlines(keepends=True)
    moved = [
        line.replace(f",{line.split(',')[1]},", f",{float(line.split(',')[1]) + 50000:.3f},", 1)
        if line[2:3] == "X" and line.split(",")[1]
        else line
        for line in lines
    ]
    path.write_text("".join(moved), encoding="utf-8")


def every_trial_fails(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every Monte Carlo trial fails (as with an absurd option the checks let through)."""
    import sim.mc
    from xmalign.montecarlo import AdaptiveStudy

    def run_study(machine: Any, chosen: Any, settings: Any, *rest: Any) -> list:
        failure = "GeometryError: no feasible plan"
        return [
            sim.mc.StrategyResult(s, AdaptiveStudy(), trials=2, failures=[failure] * 2)
            for s in chosen
        ]

    monkeypatch.setattr(sim.mc, "run_study", run_study)


_POST = ("post", "--plan", L, "--data", "m.csv", "--out", "e-new.csv")
_SQUARENESS_ROWS = (
    "EC0Y,,3.6878,urad,1.2626\nEA0Z,,-3.6786,urad,2.4545\nEB0Z,,-27.4713,urad,1.9945\n"
)
_CARELESS_USER_CASES = [
    # tracebacks: NaN or infinity in a number option (one check for every option)
    Case(
        "identify-encoder-nan",
        ("identify", "--sim", "--encoder-urad", "nan"),
        ("--encoder-urad", "not a finite number"),
    ),
    Case(
        "identify-distance-inf",
        ("identify", "--sim", "--distance-um", "inf"),
        ("--distance-um", "not a finite number"),
    ),
    Case(
        "identify-uncertainty-zero",
        ("identify", "--sim", "--tool-rotation-urad", "0"),
        ("--tool-rotation-urad", "must be positive"),
    ),
    Case(
        "identify-distance-1e300",
        ("identify", "--sim", "--distance-um", "1e300"),
        ("--distance-um", "at most 10000 um"),
    ),
    Case(
        "mc-error-scale-nan",
        ("mc", "--error-scale", "nan", "--out", "mc"),
        ("--error-scale", "nan"),
    ),
    Case(
        "serve-gamma-nan",
        ("sim", "serve", "--gamma-deg", "nan", "--interferometer-pty"),
        ("--gamma-deg", "nan"),
    ),
    Case(
        "post-index-beyond-targets",
        _POST,
        ("m.csv", "line Z run 2", "target index 99"),
        measured(_row_of_z(index=99)),
    ),
    # hangs: an impossible distance, absurd counts (the limit and why)
    Case(
        "align-distance-inf",
        ("align", "--sim", "--distance-mm", "inf", "--timeout", "2"),
        ("--distance-mm", "inf"),
    ),
    Case(
        "align-distance-1um", ("align", "--sim", "--distance-mm", "0.001"), ("--distance-mm", "20")
    ),
    Case("align-timeout-negative", ("align", "--sim", "--timeout", "-1"), ("--timeout",)),
    Case(
        "identify-alignments-100000",
        ("identify", "--sim", "--alignments", "100000"),
        ("--alignments", "at most 50", "uncertainty"),
    ),
    Case(
        "plan-identify-count-1000", ("plan-identify", "--count", "1000"), ("--count", "at most 50")
    ),
    Case(
        "dry-run-positions-999",
        ("dry-run", "--identification-positions", "999", "--out", "dr"),
        ("--identification-positions", "at most 50"),
    ),
    Case(
        "mc-vary-alignments-100",
        ("mc", "--vary", "alignments=4:100", "--out", "mc"),
        ("alignments", "'100'", "at most 50"),
    ),
    # silent: yes/no values read as 1.0 where a number is expected
    Case(
        "pose-gamma-true",
        POSE,
        (P, "gamma_deg", "yes/no"),
        edit_json(P, sets("gamma_deg", value=True)),
    ),
    Case(
        "machine-spindle-yes",
        MACHINE,
        (M, "spindle_angle_deg", "yes/no"),
        replace(M, "spindle_angle_deg: 0", "spindle_angle_deg: yes"),
    ),
    Case(
        "session-spindle-true",
        SESSION,
        (S, "spindle_angle_deg", "yes/no"),
        edit_json(S, sets("spindle_angle_deg", value=True)),
    ),
    Case(
        "session-position-false",
        SESSION,
        (S, "alignments.0.machine_mm.1", "yes/no"),
        edit_json(S, sets("alignments", 0, "machine_mm", 1, value=False)),
    ),
    Case(
        "plan-spindle-true",
        PLAN,
        (L, "spindle_angle_deg", "yes/no"),
        edit_json(L, sets("spindle_angle_deg", value=True)),
    ),
    Case(
        "units-timeout-yes",
        UNITS,
        (U, "timeouts.io_s", "yes/no"),
        replace(U, "io_s: 1.0", "io_s: yes"),
    ),
    # silent: post's data
    Case(
        "post-dead-instrument",
        _POST,
        ("m.csv", "line Z", "read exactly 0", "dead"),
        measured(_dead_z),
    ),
    Case(
        "post-run-outside-plan",
        _POST,
        ("m.csv: line ", ": line Z run 7", "runs 1..2"),
        measured(_row_of_z(run=7)),
    ),
    Case(
        "post-same-pair-twice",
        (
            "post",
            "--plan",
            L,
            "--data",
            "m.csv",
            "--plan",
            L,
            "--data",
            "m.csv",
            "--out",
            "e-new.csv",
        ),
        ("m.csv", "station 1", "station 2", "twice"),
        measured(),
    ),
    Case(
        "post-report-docx", (*_POST, "--report", "r.docx"), ("r.docx", "'.docx'", ".html or .pdf")
    ),
    Case(
        "post-report-no-extension",
        (*_POST, "--report", "record"),
        ("record", "no file name ending"),
    ),
    # silent: error tables
    Case("comp-no-squareness", ERRORS, (E, "EC0Y, EA0Z, EB0Z"), replace(E, _SQUARENESS_ROWS, "")),
    Case(
        "comp-tables-outside-travel",
        ERRORS,
        (E, "EXX", "X travel", "50255.6", "0..2000"),
        _x_tables_moved,
    ),
    # silent: mc
    Case("mc-unknown-method", ("mc", "--method", "nope", "--out", "mc"), ("--method", "'nope'")),
    Case(
        "mc-squareness-inf",
        ("mc", "--squareness-urad", "inf", "--out", "mc"),
        ("--squareness-urad", "inf"),
    ),
    Case(
        "mc-squareness-1e9",
        ("mc", "--squareness-urad", "1e9", "--out", "mc"),
        ("--squareness-urad",),
    ),
    Case(
        "mc-every-trial-fails",
        ("mc", "--trials", "2", "--batch", "2", "--out", "mc"),
        ("every trial failed", "GeometryError"),
        patch=every_trial_fails,
    ),
]


def recorded_with_seed(seed: int) -> Damage:
    """m.csv as a simulated run with ``--seed SEED`` leaves it (no point yet)."""
    return write("m.csv", f"# xmalign measurements sim_seed={seed}\n" + MEASUREMENTS_HEADER)


AS_ROOT = os.geteuid() == 0
RUN = ("run", "--sim", "--in-process", "--plan", L)
_DEVICE_CASES = [
    Case(
        "identify-out-dev-null",
        (*SESSION[:3], "--out", "nul"),
        ("nul", "--out", "character device"),
        node("nul", "null"),
    ),
    Case(
        "identify-out-dev-full",
        (*SESSION[:3], "--out", "full"),
        ("full", "--out", "character device"),
        node("full", "full"),
    ),
    Case(
        "program-plan-out-dev-null",
        (*POSE, "--plan-out", "nul"),
        ("nul", "--plan-out", "character device"),
        node("nul", "null"),
    ),
    Case(
        "run-out-dev-null",
        (*RUN, "--out", "nul"),
        ("nul", "--out", "character device"),
        node("nul", "null"),
    ),
    Case(
        "post-out-dev-null",
        (*PLAN[:5], "--out", "nul"),
        ("nul", "--out", "character device"),
        node("nul", "null"),
    ),
    Case(
        "run-controller-program-dev-null",
        _CONTROLLED_RUN,
        ("nul", "machine_position", "character device"),
        each(node("nul", "null"), _controlled_units("nul")),
    ),
    Case(
        "comp-out-a-device-in-the-folder",
        (*ERRORS, "--force"),
        ("NC_CEC.INI", "character device"),
        node("comp/NC_CEC.INI", "null"),
    ),
]
_FILES_CASES = [
    *(_DEVICE_CASES if AS_ROOT else []),
    # FIFOs and sockets: refused at once (a FIFO would block until something reads it)
    Case(
        "identify-out-fifo",
        (*SESSION[:3], "--out", "ff"),
        ("ff", "--out", "FIFO"),
        node("ff", "fifo"),
    ),
    Case(
        "run-controller-program-fifo",
        _CONTROLLED_RUN,
        ("ff", "machine_position", "FIFO"),
        each(node("ff", "fifo"), _controlled_units("ff")),
    ),
    Case(
        "run-controller-program-a-folder",
        _CONTROLLED_RUN,
        ("comp", "machine_position", "is a folder"),
        each(write("comp/x", ""), _controlled_units("comp")),
    ),
    Case(
        "identify-out-socket",
        (*SESSION[:3], "--out", "so"),
        ("so", "--out", "socket"),
        node("so", "socket"),
    ),
    Case(
        "program-out-fifo", (*POSE[:3], "--out", "ff"), ("ff", "--out", "FIFO"), node("ff", "fifo")
    ),
    Case("run-out-fifo", (*RUN, "--out", "ff"), ("ff", "--out", "FIFO"), node("ff", "fifo")),
    Case(
        "run-log-file-fifo",
        (*RUN, "--out", "new.csv", "--log-file", "ff"),
        ("ff", "--log-file", "FIFO"),
        node("ff", "fifo"),
    ),
    Case(
        "post-report-fifo",
        (*PLAN, "--report", "ff"),
        ("ff", "--report", "FIFO"),
        node("ff", "fifo"),
    ),
    Case(
        "comp-out-a-fifo-in-the-folder",
        (*ERRORS, "--force"),
        ("NC_CEC.INI", "FIFO"),
        node("comp/NC_CEC.INI", "fifo"),
    ),
    Case(
        "mc-out-a-fifo-in-the-folder",
        ("mc", "--out", "comp"),
        ("mc.json", "--out", "FIFO"),
        node("comp/mc.json", "fifo"),
    ),
    Case(
        "serve-position-file-fifo",
        ("sim", "serve", "--position-file", "ff", "--program", "run.mpf"),
        ("ff", "--position-file", "FIFO"),
        both(node("ff", "fifo"), write("run.mpf", "G0 X0\n")),
    ),
    # an output that is an input or another output, --log-file included, in every command
    Case(
        "run-log-file-is-the-plan",
        (*RUN, "--out", "new.csv", "--log-file", L),
        (L, "--log-file", "--plan", "written into"),
    ),
    Case(
        "run-log-file-is-the-out",
        (*RUN, "--out", "m.csv", "--log-file", "m.csv"),
        ("m.csv", "--log-file", "--out"),
    ),
    Case(
        "run-log-file-is-the-machine",
        (*RUN, "--out", "new.csv", "--machine", M, "--log-file", M),
        (M, "--log-file", "--machine"),
    ),
    Case(
        "run-out-is-the-program",
        (*RUN, "--out", "run.mpf", "--program", "run.mpf"),
        ("run.mpf", "--out", "--program"),
        write("run.mpf", "G0 X0\n"),
    ),
    Case(
        "run-out-a-link-to-the-plan",
        (*RUN, "--out", "link.csv"),
        ("link.csv", "--out", "--plan"),
        lambda folder: (folder / "link.csv").symlink_to(L),
    ),
    Case(
        "align-log-file-is-the-config",
        ("align", "--live", "--config", U, "--log-file", U),
        (U, "--log-file", "--config"),
    ),
    Case(
        "identify-log-file-is-the-out",
        (*SESSION[:3], "--out", "p.json", "--log-file", "p.json"),
        ("p.json", "--log-file", "--out"),
    ),
    Case(
        "serve-log-file-is-the-machine",
        ("sim", "serve", "--modbus", "127.0.0.1:0", "--machine", M, "--log-file", M),
        (M, "--log-file", "--machine"),
    ),
    Case(
        "serve-position-file-is-the-program",
        ("sim", "serve", "--position-file", "run.mpf", "--program", "run.mpf"),
        ("run.mpf", "--position-file", "--program"),
        write("run.mpf", "G0 X0\n"),
    ),
    Case(
        "serve-position-file-is-a-plan",
        ("sim", "serve", "--position-file", L, "--program", "run.mpf"),
        (L, "--position-file", "machine position"),
        write("run.mpf", "G0 X0\n"),
    ),
    Case(
        "publish-position-file-is-a-plan",
        ("sim", "publish-position", L),
        (L, "FILE", "machine position"),
    ),
    Case(
        "publish-position-file-fifo",
        ("sim", "publish-position", "ff"),
        ("ff", "FILE", "FIFO"),
        node("ff", "fifo"),
    ),
    # files a later step or the user relies on: replaced only with --force
    Case("comp-replaces-the-users-table", ERRORS, ("NC_CEC.INI", "--out", "--force")),
    Case(
        "comp-replaces-ax-eec",
        (*ERRORS[:3], "--out", "user"),
        ("AX_EEC.INI", "--force"),
        write("user/AX_EEC.INI", "; the user's own table\n"),
    ),
    Case(
        "comp-replaces-joints-ini",
        (*ERRORS[:3], "--out", "user", "--controller", "linuxcnc"),
        ("joints.ini", "--force"),
        write("user/joints.ini", "[JOINT_0]\n"),
    ),
    Case("program-replaces-the-plan", (*POSE, "--plan-out", L), (L, "--plan-out", "--force")),
    Case(
        "program-replaces-the-program",
        (*POSE[:3], "--out", "run.mpf"),
        ("run.mpf", "--out", "--force"),
        write("run.mpf", "G0 X0\n"),
    ),
    Case("identify-replaces-the-pose", (*SESSION[:3], "--out", P), (P, "--out", "--force")),
    Case(
        "identify-sim-replaces-the-session",
        ("identify", "--sim", "--session-out", S),
        (S, "--session-out", "--force"),
    ),
    # a line id the measurement CSV cannot hold
    Case(
        "run-plan-id-comma",
        (*RUN, "--out", "new.csv"),
        (L, "lines.0.id", "','"),
        edit_json(L, _line("id", "X,Y")),
    ),
    Case(
        "run-plan-id-newline",
        (*RUN, "--out", "new.csv"),
        (L, "lines.1.id", "'\\n'"),
        edit_json(L, _line("id", "Y\nZ", 1)),
    ),
    Case("post-plan-id-hash", PLAN, (L, "lines.0.id", "'#'"), edit_json(L, _line("id", "#X"))),
    Case("post-plan-id-space", PLAN, (L, "lines.0.id", "' '"), edit_json(L, _line("id", "X 1"))),
    # messages that say what is wrong
    Case(
        "run-resume-with-another-seed",
        (*RUN, "--out", "m.csv", "--resume", "--seed", "2"),
        ("--seed 2", "m.csv", "--seed 1"),
        recorded_with_seed(1),
    ),
    Case(
        "run-out-a-plan-file",
        (*RUN, "--out", "plan2.json"),
        ("plan2.json", "--out", "plan file", "not a measurement CSV"),
        lambda folder: shutil.copy(folder / L, folder / "plan2.json"),
    ),
    Case("run-out-a-pose-file", (*RUN, "--out", P), (P, "--out", "launch-pose file")),
    # --canopen 999.999.1.1: serve-canopen-not-a-group above (the canopen helper's)
]


def link(name: str, target: str) -> Damage:
    """``name`` a symbolic link to ``target`` (itself: a link that loops)."""
    return lambda folder: (folder / name).symlink_to(target)


LOOP = "symbolic link that loops"
#: ``xmalign comp --controller linuxcnc --ini`` with the INI (the argument) still to give.
LINUXCNC_INI = (*ERRORS[:3], "--controller", "linuxcnc", "--ini")
#: A LinuxCNC INI with the three joints' sections.
MILL_INI = "[KINS]\nJOINTS = 3\n\n[JOINT_0]\n\n[JOINT_1]\n\n[JOINT_2]\n"
#: Issue 32: data the commands damaged, and symlink loops that ended in a traceback.
_LINK_CASES = [
    Case(
        "import-replaces-the-tracker-file",
        (*COMMAND["spatial-analyzer.txt"][:5], "--out", "tracker.csv"),
        ("tracker.csv", "--out", "--force"),
    ),
    Case("post-replaces-the-users-tables", (*PLAN[:5], "--out", E), (E, "--out", "--force")),
    Case(
        "plan-identify-replaces-the-design",
        ("plan-identify", "--count", "4", "--out", P),
        (P, "--out", "--force"),
    ),
    Case(
        "post-out-a-link-to-the-users-file",
        (*PLAN[:5], "--out", "link.csv"),
        ("link.csv", "--out", "already exists", "--force"),
        link("link.csv", E),
    ),
    Case(
        "post-out-a-link-to-the-data",
        (*PLAN[:5], "--out", "link.csv", "--force"),
        ("link.csv", "--out", "--data"),
        link("link.csv", "m.csv"),
    ),
    Case(
        "program-plan-out-a-link-to-the-pose",
        (*POSE, "--plan-out", "link.json", "--force"),
        ("link.json", "--plan-out", "--pose"),
        link("link.json", P),
    ),
    Case(
        "comp-out-a-link-in-the-folder-to-the-errors",
        (*ERRORS, "--force"),
        ("NC_CEC.INI", "--out", "--errors"),
        each(remove("comp/NC_CEC.INI"), link("comp/NC_CEC.INI", f"../{E}")),
    ),
    Case("post-data-a-loop", (*PLAN[:4], "loop", *PLAN[5:]), ("loop", LOOP), link("loop", "loop")),
    Case(
        "post-tracker-a-loop",
        ("post", "--tracker", "loop", "--out", "e-new.csv"),
        ("loop", LOOP),
        link("loop", "loop"),
    ),
    Case(
        "post-out-a-loop",
        (*PLAN[:5], "--out", "loop"),
        ("loop", "--out", LOOP),
        link("loop", "loop"),
    ),
    Case(
        "run-plan-a-loop",
        (*RUN[:4], "loop", "--out", "new.csv"),
        ("loop", LOOP),
        link("loop", "loop"),
    ),
    Case(
        "import-points-a-loop",
        (*COMMAND["spatial-analyzer.txt"][:4], "loop", "--out", "t-new.csv"),
        ("loop", LOOP),
        link("loop", "loop"),
    ),
    Case(
        "identify-input-a-loop",
        ("identify", "--input", "loop", "--out", "p-new.json"),
        ("loop", LOOP),
        link("loop", "loop"),
    ),
    Case(
        "program-pose-a-loop", ("program", "--pose", "loop"), ("loop", LOOP), link("loop", "loop")
    ),
    Case(
        "identify-out-a-loop",
        (*SESSION[:3], "--out", "loop"),
        ("loop", "--out", LOOP),
        link("loop", "loop"),
    ),
    # comp --ini: the merged INI or a comp file in the INI's own place, even with --force
    Case(
        "comp-merged-ini-is-the-ini",
        (*LINUXCNC_INI, "cfg/mill.ini", "--out", "lc", "--force"),
        ("lc/mill-xmalign.ini", "is also the --ini file"),
        lambda folder: (
            write("cfg/mill.ini", MILL_INI)(folder),
            write("lc/.keep", "")(folder),
            link("lc/mill-xmalign.ini", "../cfg/mill.ini")(folder),
        ),
    ),
    Case(
        "comp-ini-named-like-a-comp-output",
        (*LINUXCNC_INI, "lc/joints.ini", "--out", "lc", "--force"),
        ("lc/joints.ini", "is also the --ini file"),
        write("lc/joints.ini", MILL_INI),
    ),
    Case(
        "comp-ini-without-the-joints",
        (*LINUXCNC_INI, "bare.ini", "--out", "lc"),
        ("bare.ini", "[JOINT_0]"),
        write("bare.ini", "[EMC]\nMACHINE = bare\n"),
    ),
    Case(
        "comp-ini-linear-units-unknown",
        (*LINUXCNC_INI, "furlong.ini", "--out", "lc"),
        ("furlong.ini", "[TRAJ] LINEAR_UNITS = furlong"),
        write("furlong.ini", "[TRAJ]\nLINEAR_UNITS = furlong\n\n" + MILL_INI),
    ),
]


def _alias_bomb() -> str:
    """Nine levels of nine aliases: 9**9 values once expanded, a few hundred bytes written."""
    lines = ["a0: &a0 [x, x, x, x, x, x, x, x, x]"]
    lines += [f"a{n}: &a{n} [{', '.join([f'*a{n - 1}'] * 9)}]" for n in range(1, 9)]
    return "\n".join(lines) + "\n"


_UNITS_CANOPEN_LAUNCH = "launch:\n  transport: canopen\n  channel: can0\n  node_ids: "
#: Issue 32's careless list: numbers as a person writes them, aliases, travel, node ids.
_ISSUE_32_CASES = [
    Case(
        "yaml-octal-travel",
        MACHINE,
        (M, "travel_mm.X.1' (line 7)", "leading zero"),
        replace(M, "X: [0, 2000]", "X: [0, 02000]"),
    ),
    Case(
        "yaml-octal-negative",
        MACHINE,
        (M, "travel_mm.Z.0", "leading zero"),
        replace(M, "Z: [-500, 0]", "Z: [-0500, 0]"),
    ),
    Case(
        "yaml-octal-backlash",
        MACHINE,
        (M, "cnc.backlash_um.X", "leading zero"),
        replace(M, _CNC, _CNC + "\n  backlash_um: {X: 010}"),
    ),
    Case(
        "yaml-sexagesimal-feed",
        MACHINE,
        (M, "feed_mm_min.measure", "colon"),
        replace(M, "measure: 2000", "measure: 33:20"),
    ),
    Case(
        "yaml-sexagesimal-travel",
        MACHINE,
        (M, "travel_mm.Y.1", "colon"),
        replace(M, "Y: [0, 1500]", "Y: [0, 1:30]"),
    ),
    Case("yaml-alias-bomb", MACHINE, (M, "aliases expand to more than"), append(M, _alias_bomb())),
    Case(
        "units-octal-port",
        UNITS,
        (U, "launch.port", "leading zero"),
        replace(U, "port: 502", "port: 0502"),
    ),
    Case("units-alias-bomb", UNITS, (U, "aliases expand"), append(U, _alias_bomb())),
    Case(
        "machine-reference-outside-travel",
        MACHINE,
        (M, "cnc.reference_mm", "X = 2500", "travel"),
        replace(M, _CNC, _CNC + "\n  reference_mm: [2500, 0, 0]"),
    ),
    Case(
        "units-one-node-id-twice",
        UNITS,
        (U, "receiver.node_ids", "node 3", "launch unit"),
        replace(
            U,
            "launch:\n  transport: modbus-tcp\n  host: 192.168.10.11\n  port: 502\n  device_id: 1",
            _UNITS_CANOPEN_LAUNCH + "[3, 9]",
        ),
    ),
    Case(
        "units-node-id-twice-in-a-unit",
        UNITS,
        (U, "launch.node_ids", "node 7"),
        replace(
            U,
            "launch:\n  transport: modbus-tcp\n  host: 192.168.10.11\n  port: 502\n  device_id: 1",
            _UNITS_CANOPEN_LAUNCH + "[7, 7]",
        ),
    ),
]


def _second_station(make: Callable[[Path, Path], None]) -> Damage:
    """m.csv measured, and m2.csv made from it by ``make(m.csv, m2.csv)``."""

    def apply(folder: Path) -> None:
        measured()(folder)
        make(folder / "m.csv", folder / "m2.csv")

    return apply


_TWO_STATIONS = ("post", "--plan", L, "--data", "m.csv", "--plan", L, "--data", "m2.csv")
_ISSUE_32_CASES += [
    Case(
        "post-second-station-a-copy",
        (*_TWO_STATIONS, "--out", "e-new.csv"),
        ("m2.csv", "station 2", "station 1", "m.csv", "copy of it"),
        _second_station(lambda a, b: shutil.copy(a, b)),
    ),
    Case(
        "post-second-station-a-symlink",
        (*_TWO_STATIONS, "--out", "e-new.csv"),
        ("m2.csv", "station 2", "station 1", "m.csv", "copy of it"),
        _second_station(lambda a, b: b.symlink_to(a.name)),
    ),
]

_ISSUE_32_CASES += [
    Case(
        "program-points-out-without-instrument",
        ("program", "--pose", P, "--out", "run.mpf", "--points-out", "points-new.csv"),
        ("--points-out", "not used without --instrument"),
    ),
    Case(
        "program-tracker-with-lines",
        ("program", "--instrument", "tracker", "--lines", "X,Y", "--out", "t.nc"),
        ("--lines", "not used with --instrument tracker"),
    ),
    Case(
        "dry-run-tracker-two-stations",
        ("dry-run", "--instrument", "tracker", "--stations", "2", "--out", "dr"),
        ("--stations", "not used with --instrument tracker"),
    ),
    Case(
        "mc-instruments-on-a-scheduler",
        ("mc", "--mode", "instruments", "--trials", "1", "--scheduler", "tcp://127.0.0.1:9"),
        ("--scheduler", "not used with --mode instruments"),
    ),
    Case(
        "dry-run-tracer-verify",
        ("dry-run", "--instrument", "tracer", "--verify", "--out", "dr"),
        ("--verify", "not used with --instrument tracer"),
    ),
    # an ignored option given with its default value is refused too (it was not: only a
    # value other than the default was seen)
    Case(
        "dry-run-tracker-shop-given-as-the-default",
        ("dry-run", "--instrument", "tracker", "--shop", "drifting", "--out", "dr"),
        ("--shop", "not used with --instrument tracker"),
    ),
    Case(
        "dry-run-tracer-one-station-given",
        ("dry-run", "--instrument", "tracer", "--stations", "1", "--out", "dr"),
        ("--stations", "not used with --instrument tracer"),
    ),
    Case(
        "dry-run-tracker-six-positions-given",
        ("dry-run", "--instrument", "tracker", "--identification-positions", "6", "--out", "dr"),
        ("--identification-positions", "not used with --instrument tracker"),
    ),
    Case(
        "mc-instruments-batch-given-as-the-default",
        ("mc", "--mode", "instruments", "--trials", "1", "--batch", "20", "--out", "mc-new"),
        ("--batch", "not used with --mode instruments"),
    ),
    Case(
        "mc-instruments-method-given-as-the-default",
        ("mc", "--mode", "instruments", "--trials", "1", "--method", "joint", "--out", "mc-new"),
        ("--method", "not used with --mode instruments"),
    ),
    Case(
        "mc-instruments-workers-given-as-the-default",
        ("mc", "--mode", "instruments", "--trials", "1", "--workers", "0", "--out", "mc-new"),
        ("--workers", "not used with --mode instruments"),
    ),
    Case(
        "program-points-out-history-exists",
        ("program", "--instrument", "tracker", "--out", "t.nc", "--points-out", "pts.csv"),
        ("pts.csv.history", "--points-out", "--force"),
        write("pts.csv.history", "the user's notes\n"),
    ),
    Case(
        "dry-run-two-stations-verify",
        ("dry-run", "--stations", "2", "--verify", "--out", "dr"),
        ("--verify is for one station",),
    ),
    Case(
        "run-live-with-a-seed",
        (*_CONTROLLED_RUN, "--seed", "1"),
        ("--seed", "not used without --sim"),
    ),
    Case(
        "run-live-with-a-shop",
        (*_CONTROLLED_RUN, "--shop", "drifting"),
        ("--shop", "not used without --sim"),
    ),
    Case(
        "run-live-with-a-program",
        (*_CONTROLLED_RUN, "--program", "run.mpf", "--dialect", "sinumerik"),
        ("--program", "not used without --sim"),
    ),
    Case(
        "program-a-pose-of-another-machine",
        POSE,
        (P, "was made for machine 'Other mill'", "the reference machine", "pose was made with"),
        edit_json(P, sets("machine", value="Other mill")),
    ),
    Case(
        "program-a-pose-of-another-geometry",
        POSE,
        (P, "machine_sha256 000000000000...", "pose was made with"),
        edit_json(
            P,
            lambda d: d.update(machine="Example FYXZ gantry mill", machine_sha256="0" * 64),
        ),
    ),
    Case(
        "program-tracker-with-the-default-pose",
        ("program", "--instrument", "tracker", "--pose", "pose.json", "--out", "t.nc"),
        ("--pose", "not used with --instrument tracker"),
    ),
]

CASES = (
    _generic_cases()
    + _kind_cases()
    + _same_file_cases()
    + _STREAM_CASES
    + _CLI_CASES
    + _CARELESS_USER_CASES
    + _FILES_CASES
    + _LINK_CASES
    + _ISSUE_32_CASES
)


# -- running a case -----------------------------------------------------------------------


def prepare(folder: Path) -> None:
    """A copy of every example file and an (empty) measurement CSV; comp/ holds old output."""
    for name in EXAMPLES:
        shutil.copy(ROOT / "examples" / name, folder / name)
    (folder / "m.csv").write_text(MEASUREMENTS_HEADER, encoding="utf-8")
    (folder / "comp").mkdir()
    (folder / "comp" / "NC_CEC.INI").write_text("old table\n", encoding="utf-8")
    (folder / "pose-old.json").write_text("{}\n", encoding="utf-8")
    (folder / "points.csv").write_text(_point_list(), encoding="utf-8")


def _point_list() -> str:
    """The point list ``program --instrument tracker --points-out`` writes (import reads it)."""
    from trajectories.instruments import InstrumentProgram, point_list_csv, tracker_points
    from xmalign.machine import default_machine_path, load_machine

    machine = load_machine(default_machine_path())
    return point_list_csv(InstrumentProgram(points_mm=tracker_points(machine)), machine.smr_offset)


def hashes(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def run_main(argv: tuple[str, ...]) -> tuple[int | None, str, str]:
    """``xmalign ARGV`` in this process: exit code (None for an escaped exception), stderr."""
    from xmalign.cli import main

    stderr, stdout = io.StringIO(), io.StringIO()
    code: int | None = 0
    escaped = ""
    saved = sys.argv
    sys.argv = ["xmalign", *argv]
    try:
        with redirect_stderr(stderr), redirect_stdout(stdout):
            main()
    except SystemExit as stop:
        code = stop.code if isinstance(stop.code, int) else (0 if stop.code is None else 1)
    except BaseException:  # noqa: BLE001 - what a user would see as a traceback
        code, escaped = None, traceback.format_exc()
    finally:
        sys.argv = saved
    return code, stderr.getvalue(), escaped


def run_case(case: Case, folder: Path, monkeypatch: pytest.MonkeyPatch) -> Outcome:
    prepare(folder)
    if case.damage is not None:
        case.damage(folder)
    before = hashes(folder)
    monkeypatch.chdir(folder)
    with monkeypatch.context() as patched:
        if case.patch is not None:
            case.patch(patched)
        code, stderr, escaped = run_main(case.argv)
    after = hashes(folder)
    damaged = [name for name, digest in before.items() if after.get(name) != digest]
    leftovers = [name for name in after if name.endswith(".tmp")]
    lines = [line for line in stderr.splitlines() if line.strip()]
    return Outcome(code, lines, escaped or ("Traceback" in stderr) * stderr, damaged, leftovers)


def verdict(case: Case, outcome: Outcome) -> str:
    """``clean``, ``traceback``, ``accepted`` (wrongly) or ``unclear`` (several lines)."""
    if outcome.traceback:
        return "traceback"
    if outcome.code == 0:
        return "accepted"
    one_line = len(outcome.stderr_lines) == 1
    named = one_line and all(f in outcome.stderr_lines[0] for f in case.fragments)
    return "clean" if outcome.code == case.code and named else "unclear"
