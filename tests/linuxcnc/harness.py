"""Headless LinuxCNC 2.9 (Debian ``linuxcnc-uspace``) as a test partner.

Usage::

    from harness import SimMachine, linuxcnc_available, run_linuxcnc, write_sim_config

    ini = write_sim_config(tmp_dir, SimMachine(coordinates="XYYZ"))
    run = run_linuxcnc(ini, [
        {"op": "estop_reset"}, {"op": "machine_on"}, {"op": "home"},
        {"op": "mdi", "gcode": "G53 G0 X10 Y20 Z-5"},
        {"op": "pins", "names": ["joint.0.pos-cmd"], "label": "at"},
        {"op": "run", "program": str(ngc), "watch": ["joint.0.f-error"]},
    ])
    run.value("at")["joint.0.pos-cmd"]

Actions (run in order by ``display.py``; the first that fails ends the list):
``estop_reset``, ``machine_on``, ``home``, ``estop``, ``unhome`` (all joints), ``mdi``
(``gcode``; waits until idle and in position), ``pins`` (``names``: ``hal.get_value`` of each),
``setp`` (``name``, ``value``), ``sleep`` (``seconds``), ``run`` (``program``:
runs it to the end, resuming after every M0; ``watch``: pins whose largest
absolute value is returned; ``feed_override``: set before the start;
``standstill_joints``: N records, whenever joints 0..N-1 all stand still, each
joint's ``pos-cmd``, ``motor-pos-cmd``, ``motor-offset`` and the direction of
its last move, from the ``direction_latches`` of :class:`SimMachine`). Every
action may carry a ``label``.

LinuxCNC refuses to run as root: as root the harness runs it as the user
``XMALIGN_LINUXCNC_USER`` (default ``xmcnc``, created with ``useradd`` when
missing); otherwise as the current user. Only one LinuxCNC runs per host: every
start holds ``flock /tmp/xmalign-linuxcnc.flock`` until the previous instance's
processes are gone.

:func:`linuxcnc_serving` starts a LinuxCNC whose display is ``linuxcncrsh``
(``write_sim_config(..., display="linuxcncrsh --port P")``) and keeps it
running for the ``with`` block: other processes command it over TCP.
:func:`linuxcnc_publishing` adds ``xmalign sim publish-position``, which keeps
LinuxCNC's actual position in a file for ``xmalign sim serve --follow-position-file``.
"""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import signal
import socket
import subprocess
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from cli_helpers import Process

#: The host-wide lock every start of LinuxCNC takes (``flock`` on the command line, the
#: same ``fcntl.flock`` here), so that tests, CI and other helpers never start two.
LOCK_PATH = Path("/tmp/xmalign-linuxcnc.flock")
USER = os.environ.get("XMALIGN_LINUXCNC_USER", "xmcnc")
SYSTEM_PYTHON = Path("/usr/bin/python3")
DISPLAY_SCRIPT = Path(__file__).resolve().parent / "display.py"
#: Processes of a LinuxCNC instance that outlive ``linuxcnc`` for a few seconds.
LINGERING = ("linuxcncsvr", "milltask", "rtapi_app", "io", "iov2", "halui")
AXES = ("X", "Y", "Z")


def linuxcnc_available() -> bool:
    """True when ``linuxcnc`` and its Python modules (system Python) are installed."""
    if shutil.which("linuxcnc") is None or not SYSTEM_PYTHON.exists():
        return False
    probe = subprocess.run(
        [str(SYSTEM_PYTHON), "-c", "import linuxcnc, hal"], capture_output=True, check=False
    )
    return probe.returncode == 0


def halcompile_available() -> bool:
    """True when ``halcompile`` (Debian ``linuxcnc-uspace-dev``) is installed."""
    return shutil.which("halcompile") is not None


def run_as_user() -> str | None:
    """The user to run LinuxCNC as (created when missing), or None to run as ourselves."""
    if os.geteuid() != 0:
        return None
    known = subprocess.run(["getent", "passwd", USER], capture_output=True, check=False)
    if known.returncode != 0:
        subprocess.run(["useradd", "--create-home", USER], check=True, capture_output=True)
    return USER


def halcmd(*words: str) -> None:
    """``halcmd`` as the user LinuxCNC runs as (its HAL belongs to that user)."""
    user = run_as_user()
    command = [*(["runuser", "-u", user, "--"] if user else []), "halcmd", *words]
    subprocess.run(command, check=True, capture_output=True, timeout=30)


@dataclass(frozen=True)
class SimMachine:
    """A simulated trivkins machine: joints loop their command back as feedback.

    ``coordinates`` names each joint's axis (``XYZ``; ``XYYZ`` is LinuxCNC's
    gantry with two Y joints). Travel limits (mm) are the same for the axis and
    its joints; every joint is homed where it stands (at 0, which must lie in
    the travel). LinuxCNC checks the following error against ``ferror_mm`` in
    every servo period.
    """

    coordinates: str = "XYZ"
    travel_mm: dict[str, tuple[float, float]] = field(
        default_factory=lambda: {"X": (0.0, 400.0), "Y": (0.0, 300.0), "Z": (-200.0, 0.0)}
    )
    max_velocity_mm_s: float = 1000.0
    max_acceleration_mm_s2: float = 10000.0
    #: following error limit (FERROR = MIN_FERROR); beyond it LinuxCNC turns the machine off
    ferror_mm: float = 1.0
    #: [DISPLAY] MAX_FEED_OVERRIDE: the largest feed override a ``run`` action may set
    max_feed_override: float = 1.0
    #: a ``comp`` comparator per joint latching the sign of ``joint.N.vel-cmd`` every servo
    #: period (``comp.N.out``: TRUE after a positive move, held at standstill). Velocities
    #: below 1e-6 mm/s are not moves: with offsets active, a joint that the program does
    #: not move sees rounding velocities of that size while other joints move (seen on
    #: Y, < 5e-7 mm/s, during a Z move); they flip LinuxCNC's ``backlash-corr`` too, but
    #: its ``backlash-filt`` (what reaches the motor) stayed at the physical direction's value.
    direction_latches: bool = False
    #: each joint's drive is a ``scale`` (gain 1) at the start of the servo thread, so its
    #: feedback in a period is the command of the period before, as with a real drive
    #: whose position is read at the start of the period (``hm2.read``,
    #: ``stepgen.capture-position``); False: the command is netted straight to the
    #: feedback, which anything after the motion controller reads in the same period.
    #: With ``drive_lag`` a ``minmax`` per joint (``drive-range-N.min``/``max``) tracks
    #: every command the drive was sent since the start.
    drive_lag: bool = False
    #: [TRAJ] LINEAR_UNITS and the joints' units: ``inch`` writes every length of the INI
    #: (travel, velocity, acceleration, following error) in inches; the fields stay in mm
    linear_units: Literal["mm", "inch"] = "mm"

    @property
    def joints(self) -> int:
        return len(self.coordinates)

    @property
    def units_per_mm(self) -> float:
        """LinuxCNC's ``linear_units``: machine units per mm."""
        return 1.0 if self.linear_units == "mm" else 1.0 / 25.4


@contextmanager
def braking_at(machine: SimMachine, acceleration_mm_s2: float) -> Iterator[None]:
    """The running LinuxCNC of ``machine`` plans its moves with ``acceleration_mm_s2``
    meanwhile (trajectory, axes, joints), its own after: LinuxCNC's ``ini.*`` HAL pins,
    which G-code and MDI commands take as each is processed (milltask(1))."""

    def set_to(mm_s2: float) -> None:
        pins = [
            "ini.traj_default_acceleration",
            "ini.traj_max_acceleration",
            *(f"ini.{axis.lower()}.max_acceleration" for axis in AXES),
            *(f"ini.{joint}.max_acceleration" for joint in range(machine.joints)),
        ]
        for pin in pins:
            halcmd("setp", pin, f"{mm_s2 * machine.units_per_mm}")

    set_to(acceleration_mm_s2)
    try:
        yield
    finally:
        set_to(machine.max_acceleration_mm_s2)


def _ini_text(machine: SimMachine, halfile: str, display: str = "./display.py") -> str:
    unit = machine.units_per_mm
    v, a = machine.max_velocity_mm_s * unit, machine.max_acceleration_mm_s2 * unit
    gantry = len(set(machine.coordinates)) < machine.joints
    sections = [
        ("EMC", {"VERSION": "1.1", "MACHINE": "xmalign-harness", "DEBUG": "0"}),
        (
            "DISPLAY",
            {
                "DISPLAY": display,
                "CYCLE_TIME": "0.100",
                "MAX_FEED_OVERRIDE": f"{machine.max_feed_override}",
            },
        ),
        ("TASK", {"TASK": "milltask", "CYCLE_TIME": "0.001"}),
        ("RS274NGC", {"PARAMETER_FILE": "sim.var"}),
        ("EMCMOT", {"EMCMOT": "motmod", "COMM_TIMEOUT": "1.0", "SERVO_PERIOD": "1000000"}),
        ("HAL", {"HALFILE": halfile}),
        (
            "KINS",
            {
                "KINEMATICS": f"trivkins coordinates={machine.coordinates.lower()}"
                + (" kinstype=BOTH" if gantry else ""),
                "JOINTS": str(machine.joints),
            },
        ),
        (
            "TRAJ",
            {
                "COORDINATES": " ".join(machine.coordinates),
                "LINEAR_UNITS": machine.linear_units,
                "ANGULAR_UNITS": "degree",
                "DEFAULT_LINEAR_VELOCITY": f"{v}",
                "MAX_LINEAR_VELOCITY": f"{v}",
                "DEFAULT_LINEAR_ACCELERATION": f"{a}",
                "MAX_LINEAR_ACCELERATION": f"{a}",
            },
        ),
        ("EMCIO", {"EMCIO": "io", "CYCLE_TIME": "0.100", "TOOL_TABLE": "sim.tbl"}),
    ]
    for axis in AXES:
        low, high = (limit * unit for limit in machine.travel_mm[axis])
        sections.append(
            (
                f"AXIS_{axis}",
                {
                    "MAX_VELOCITY": f"{v}",
                    "MAX_ACCELERATION": f"{a}",
                    "MIN_LIMIT": f"{low}",
                    "MAX_LIMIT": f"{high}",
                },
            )
        )
    for joint, axis in enumerate(machine.coordinates):
        low, high = (limit * unit for limit in machine.travel_mm[axis])
        sequence = -1 if gantry and machine.coordinates.count(axis) > 1 else 0
        sections.append(
            (
                f"JOINT_{joint}",
                {
                    "TYPE": "LINEAR",
                    "MAX_VELOCITY": f"{v}",
                    "MAX_ACCELERATION": f"{a}",
                    "MIN_LIMIT": f"{low}",
                    "MAX_LIMIT": f"{high}",
                    "FERROR": f"{machine.ferror_mm * unit}",
                    "MIN_FERROR": f"{machine.ferror_mm * unit}",
                    "HOME": "0.0",
                    "HOME_OFFSET": "0.0",
                    "HOME_SEARCH_VEL": "0",
                    "HOME_LATCH_VEL": "0",
                    "HOME_SEQUENCE": f"{sequence}",
                },
            )
        )
    lines = []
    for name, keys in sections:
        lines += [f"[{name}]", *(f"{key} = {value}" for key, value in keys.items()), ""]
    return "\n".join(lines)


#: |vel-cmd| above which a direction latch takes a joint to be moving, mm/s
MOVE_THRESHOLD_MM_S = 1e-6


def _hal_text(machine: SimMachine) -> str:
    lines = [
        "# xmalign test harness: trivkins sim, each joint's command looped back as feedback",
        "loadrt [KINS]KINEMATICS",
        "loadrt [EMCMOT]EMCMOT servo_period_nsec=[EMCMOT]SERVO_PERIOD num_joints=[KINS]JOINTS",
        *(_lagging_drives(machine.joints) if machine.drive_lag else []),
        "addf motion-command-handler servo-thread",
        "addf motion-controller servo-thread",
        "net estop-loop iocontrol.0.user-enable-out iocontrol.0.emc-enable-in",
        "net tool-prep-loop iocontrol.0.tool-prepare iocontrol.0.tool-prepared",
        "net tool-change-loop iocontrol.0.tool-change iocontrol.0.tool-changed",
    ]
    if not machine.drive_lag:
        lines += [
            f"net j{joint}pos joint.{joint}.motor-pos-cmd => joint.{joint}.motor-pos-fb"
            for joint in range(machine.joints)
        ]
    if machine.direction_latches:
        lines.append(f"loadrt comp count={machine.joints}")
        for joint in range(machine.joints):
            lines += [
                f"addf comp.{joint} servo-thread",
                f"net j{joint}vel joint.{joint}.vel-cmd => comp.{joint}.in1",
                f"setp comp.{joint}.hyst {2 * MOVE_THRESHOLD_MM_S}",
            ]
    return "\n".join(lines) + "\n"


def _lagging_drives(joints: int) -> list[str]:
    """Drives answering a period late, and a record of their commands (see drive_lag)."""
    drives = ",".join(f"drive-{j}" for j in range(joints))
    ranges = ",".join(f"drive-range-{j}" for j in range(joints))
    lines = [f"loadrt scale names={drives}", f"loadrt minmax names={ranges}"]
    for j in range(joints):
        lines += [
            f"addf drive-{j} servo-thread",
            f"addf drive-range-{j} servo-thread",
            f"setp drive-{j}.gain 1",
            f"setp drive-{j}.offset 0",
            f"net j{j}cmd joint.{j}.motor-pos-cmd => drive-{j}.in drive-range-{j}.in",
            f"net j{j}fb drive-{j}.out => joint.{j}.motor-pos-fb",
        ]
    return lines


def write_sim_config(
    folder: Path,
    machine: SimMachine | None = None,
    display: str = "./display.py",
) -> Path:
    """Write an INI, its HAL file, a tool table and the display into ``folder``.

    ``display`` is the INI's ``[DISPLAY] DISPLAY`` (default the harness display,
    which :func:`run_linuxcnc` drives; ``linuxcncrsh ...`` for :func:`linuxcnc_serving`).

    The folder is made writable for the LinuxCNC user (LinuxCNC writes its
    parameter file there). Returns the INI's path (``folder/sim.ini``).
    """
    machine = machine or SimMachine()
    folder.mkdir(parents=True, exist_ok=True)
    folder.chmod(0o777)
    (folder / "sim.hal").write_text(_hal_text(machine))
    (folder / "sim.tbl").write_text("T1 P1 D0 Z0 ;\n")
    (folder / "sim.ini").write_text(_ini_text(machine, "sim.hal", display))
    shutil.copy(DISPLAY_SCRIPT, folder / DISPLAY_SCRIPT.name)
    (folder / DISPLAY_SCRIPT.name).chmod(0o755)
    return folder / "sim.ini"


def share_with_linuxcnc_user(folder: Path) -> None:
    """Let the LinuxCNC user write ``folder`` and read every file in it.

    (xmalign writes its files through a private temporary file, mode 0600.)
    """
    folder.chmod(0o777)
    for path in folder.iterdir():
        if path.is_file():
            path.chmod(path.stat().st_mode | 0o444)


@dataclass
class LinuxCNCRun:
    """What one LinuxCNC start produced.

    ``report`` is what the display wrote (None when LinuxCNC never started it):
    ``results`` (one record per action run: ``op``, ``label``, ``ok``,
    ``value`` or ``error``), ``messages`` (LinuxCNC's error channel),
    ``state`` (task state, estop, enabled, homed) and ``crash``.
    """

    returncode: int | None
    output: str
    report: dict[str, Any] | None

    @property
    def results(self) -> list[dict[str, Any]]:
        return [] if self.report is None else self.report["results"]

    def value(self, label: str) -> Any:
        """The value of the action labelled ``label``; AssertionError if it failed."""
        for record in self.results:
            if record["label"] == label:
                assert record["ok"], f"{label}: {record.get('error')}\n{self.output}"
                return record.get("value")
        raise AssertionError(f"no action labelled {label!r} ran:\n{self.describe()}")

    def failed(self) -> dict[str, Any] | None:
        """The record of the action that failed, if one did."""
        return next((r for r in self.results if not r["ok"]), None)

    def describe(self) -> str:
        return f"returncode {self.returncode}\nreport {json.dumps(self.report)}\n{self.output}"


def _ancestors() -> set[int]:
    """This process and its parents, grandparents, ... (from /proc)."""
    pids, pid = set(), os.getpid()
    while pid > 1 and pid not in pids:
        pids.add(pid)
        try:
            stat = Path(f"/proc/{pid}/stat").read_text()
        except OSError:
            break
        pid = int(stat.rsplit(")", 1)[1].split()[1])
    return pids


def _held_by_an_ancestor(path: Path) -> bool:
    """A ``flock`` command around this test run holds ``path`` (/proc/locks names its pid)."""
    try:
        inode = path.stat().st_ino
        table = Path("/proc/locks").read_text().splitlines()
    except OSError:
        return False
    holders = {
        int(fields[4])
        for fields in (line.split() for line in table)
        if len(fields) > 5 and fields[1] == "FLOCK" and fields[5].endswith(f":{inode}")
    }
    return bool(holders & _ancestors())


@contextmanager
def host_lock(timeout_s: float = 600.0) -> Iterator[None]:
    """Hold the host-wide LinuxCNC lock (other helpers' runs wait on the same file).

    Run under ``flock /tmp/xmalign-linuxcnc.flock pytest ...``, the lock is
    already this run's: then the workers of the run take a second file among
    themselves, so that they too start one LinuxCNC at a time.
    """
    path = LOCK_PATH
    with open(path, "a"):
        pass
    if _held_by_an_ancestor(path):
        path = path.with_name(path.name + ".workers")
    with open(path, "a") as stream:
        with suppress(PermissionError):  # created by another user: already shared
            os.chmod(path, 0o666)
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                fcntl.flock(stream, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    raise TimeoutError(f"{path} held for more than {timeout_s} s") from None
                time.sleep(0.2)
        try:
            yield
        finally:
            fcntl.flock(stream, fcntl.LOCK_UN)


def _lingering(user: str | None) -> list[str]:
    owner = ["-u", user] if user else ["-u", str(os.geteuid())]
    found = []
    for name in LINGERING:
        probe = subprocess.run(["pgrep", *owner, "-x", name], capture_output=True, text=True)
        found += probe.stdout.split()
    return found


def _wait_gone(user: str | None, timeout_s: float) -> list[str]:
    deadline = time.monotonic() + timeout_s
    while (left := _lingering(user)) and time.monotonic() < deadline:
        time.sleep(0.2)
    return left


def run_linuxcnc(
    ini: Path, actions: Sequence[dict[str, Any]], *, timeout_s: float = 120.0
) -> LinuxCNCRun:
    """Start ``linuxcnc -r ini``, let the harness display run ``actions``, wait for the end.

    The INI's ``[DISPLAY] DISPLAY`` must be the harness display (as
    :func:`write_sim_config` writes it). Holds the host lock for the whole run
    and returns once the instance's processes are gone.
    """
    folder = ini.resolve().parent
    share_with_linuxcnc_user(folder)
    actions_path, result_path = folder / "harness-actions.json", folder / "harness-result.json"
    actions_path.write_text(json.dumps(list(actions)))
    actions_path.chmod(0o644)
    result_path.unlink(missing_ok=True)
    user = run_as_user()
    environment = [
        f"XMALIGN_HARNESS_ACTIONS={actions_path}",
        f"XMALIGN_HARNESS_RESULT={result_path}",
        f"HOME={Path('~' + user).expanduser() if user else Path.home()}",
    ]
    command = _linuxcnc_command(ini, user, environment)
    with host_lock():
        _wait_gone(user, 30.0)
        process = subprocess.Popen(
            command,
            cwd=folder,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            text=True,
            start_new_session=True,
        )
        try:
            output, _ = process.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, 15)
            output, _ = process.communicate()
            output += f"\n[harness] linuxcnc killed after {timeout_s} s"
        left = _wait_gone(user, 20.0)
        if left:
            output += f"\n[harness] processes still running after the end: {left}"
    report = json.loads(result_path.read_text()) if result_path.exists() else None
    return LinuxCNCRun(process.returncode, output, report)


def _linuxcnc_command(ini: Path, user: str | None, environment: list[str]) -> list[str]:
    command = ["env", *environment, "linuxcnc", "-r", str(ini.resolve())]
    return ["runuser", "-u", user, "--", *command] if user else command


def _listening(port: int) -> bool:
    with socket.socket() as probe:
        probe.settimeout(0.5)
        return probe.connect_ex(("127.0.0.1", port)) == 0


@contextmanager
def linuxcnc_serving(ini: Path, port: int, *, start_timeout_s: float = 60.0) -> Iterator[Path]:
    """A LinuxCNC whose display is linuxcncrsh on ``port``, running for the ``with`` block.

    Holds the host lock from the start until its processes are gone again;
    yields the file LinuxCNC's output goes to. The end is SIGTERM to the
    process group (``linuxcnc`` shuts its processes down on it).
    """
    folder = ini.resolve().parent
    share_with_linuxcnc_user(folder)
    user = run_as_user()
    home = Path("~" + user).expanduser() if user else Path.home()
    output_path = folder / "linuxcnc-output.txt"
    with host_lock(), open(output_path, "w") as output:
        _wait_gone(user, 30.0)
        process = subprocess.Popen(
            _linuxcnc_command(ini, user, [f"HOME={home}"]),
            cwd=folder,
            stdout=output,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
        )
        try:
            deadline = time.monotonic() + start_timeout_s
            while not _listening(port):
                if process.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(
                        f"linuxcncrsh did not listen on {port}:\n{output_path.read_text()}"
                    )
                time.sleep(0.2)
            yield output_path
        finally:
            with suppress(ProcessLookupError):
                os.killpg(process.pid, signal.SIGTERM)
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()
            _wait_gone(user, 20.0)


def bring_up(client: Any, timeout_s: float = 30.0) -> None:
    """Play the operator over a linuxcncrsh session ``client`` (an enabled
    ``firmware_iface.linuxcncrsh.LinuxCnc``): E-stop reset, machine on, home all joints."""
    for command in ("estop off", "machine on", "mode manual", "home -1"):
        client._set(command)
    deadline = time.monotonic() + timeout_s
    while client._get("joint_homed")[:3] != ["YES"] * 3:
        assert time.monotonic() < deadline, "LinuxCNC did not home"
        time.sleep(0.1)


def standard_start() -> list[dict[str, Any]]:
    """Estop reset, machine on, home all joints."""
    return [{"op": "estop_reset"}, {"op": "machine_on"}, {"op": "home"}]


@contextmanager
def linuxcnc_publishing(ini: Path, port: int, position_file: Path) -> Iterator[Process]:
    """:func:`linuxcnc_serving`, and ``xmalign sim publish-position position_file``
    keeping LinuxCNC's actual position there for ``sim serve --follow-position-file``.

    The publisher is started from this process once LinuxCNC is up, as a user starts
    it on the LinuxCNC computer (LinuxCNC's user here cannot reach the project's
    Python); yields it. After the block, LinuxCNC stopped, it must have ended by
    itself within 30 s (AssertionError otherwise; it is stopped then).
    """
    publisher = None
    try:
        with linuxcnc_serving(ini, port):
            publisher = Process(["sim", "publish-position", str(position_file)], ini.parent)
            publisher.wait_for("publishing the position")
            yield publisher
    finally:
        if publisher is not None:
            try:
                publisher.finish(timeout_s=30)
            except subprocess.TimeoutExpired:
                publisher.stop()
                raise AssertionError(
                    f"publish-position went on after LinuxCNC stopped:\n{publisher.said()}"
                ) from None
