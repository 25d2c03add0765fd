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
import shutil
import sys
import traceback
from collections.abc import Callable
from contextlib import redirect_stderr, redirect_stdout
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ("fyxz.yaml", "units.yaml", "session.json", "pose.json", "plan.json", "errors.csv")
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
    ("format-2", replace(U, "format: xmalign.units/1", "format: xmalign.units/2"), "version"),
    ("rate-nan", replace(U, "rate_hz: 50", "rate_hz: .nan"), "rate_hz"),
    ("mtconnect-missing", replace(U, "source: prompt", "source: mtconnect"), "mtconnect"),
    (
        "mtconnect-ftp",
        replace(U, "source: prompt", "source: mtconnect\n  mtconnect: {url: 'ftp://a'}"),
        "mtconnect.url",
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
    ("format-9", edit_json(P, sets("format", value="xmalign.launch-pose/9")), "version '9'"),
]

L = "plan.json"
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


def _kind_cases() -> list[Case]:
    cases = []
    for prefix, argv, table in (
        (M, MACHINE, _MACHINE_CASES),
        (U, UNITS, _UNITS_CASES),
        (S, SESSION, _SESSION_CASES),
        (P, POSE, _POSE_CASES),
        (L, PLAN, _PLAN_CASES),
        (E, ERRORS, _ERROR_CASES),
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
        ("comp", "--errors", E, "--out", "comp"),
        ("comp", "permission denied"),
        patch=read_only_folder,
    ),  # noqa: E501
    Case(
        "identify-out-read-only",
        ("identify", "--input", S, "--out", "pose-old.json"),
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
        ("comp", "--errors", E, "--out", "comp"),
        ("comp", "disk full"),
        patch=full_disk,
    ),  # noqa: E501
    Case(
        "identify-full-disk",
        ("identify", "--input", S, "--out", "pose-old.json"),
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
        patch=ctrl_c_in("xmalign.cli.identify", "identify"),
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

CASES = _generic_cases() + _kind_cases() + _CLI_CASES


# -- running a case -----------------------------------------------------------------------


def prepare(folder: Path) -> None:
    """A copy of every example file and an (empty) measurement CSV; comp/ holds old output."""
    for name in EXAMPLES:
        shutil.copy(ROOT / "examples" / name, folder / name)
    (folder / "m.csv").write_text(MEASUREMENTS_HEADER, encoding="utf-8")
    (folder / "comp").mkdir()
    (folder / "comp" / "NC_CEC.INI").write_text("old table\n", encoding="utf-8")
    (folder / "pose-old.json").write_text("{}\n", encoding="utf-8")


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
