"""Outputs that would destroy something, and the messages of a run that stops (issue 22).

The one-line refusals are cases of the bad-input table (tests/xmalign/bad_input_cases.py,
section "outputs that would destroy something"); here what the table cannot express:
a device node or FIFO is still what it was, a lock held by another process (util-linux
``flock``), a disk that fills up during a run, folders never made for bad options, a
post whose report fails writes no tables. Device nodes are made with ``mknod`` in a
temporary folder (root only), never the real /dev/null.
"""

from __future__ import annotations

import contextlib
import errno
import os
import stat
import subprocess
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from bad_input_cases import _FILES_CASES, Case, hashes, prepare, run_case
from cli_helpers import run_in_process

import xmalign.formats.measurements as measurements_module
from sim.machine import VirtualMachine
from sim.synthetic import measure, six_line_plan
from xmalign.calibration import capture_sequence
from xmalign.errors import InputError, OutputError
from xmalign.formats.common import atomic_write_text
from xmalign.formats.measurements import (
    MeasurementWriter,
    RunLock,
    load_measurements,
    write_measurements,
)
from xmalign.formats.plan import read_plan, write_plan
from xmalign.rigid_body import Chain

ROOT = Path(__file__).resolve().parents[2]


def _kind(path: Path) -> int:
    return stat.S_IFMT(os.lstat(path).st_mode)


NODE_CASES = [case for case in _FILES_CASES if any(k in case.id for k in ("dev-", "fifo", "sock"))]


@pytest.mark.parametrize("case", NODE_CASES, ids=lambda case: case.id)
def test_a_device_fifo_or_socket_stays_what_it_was(
    case: Case, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """What /dev/null became as root: a regular file renamed over the device node."""
    nodes: dict[Path, int] = {}
    assert case.damage is not None

    def damage_and_note(folder: Path) -> None:
        case.damage(folder)  # type: ignore[misc]
        nodes.update({p: _kind(p) for p in folder.rglob("*") if not p.is_file() and not p.is_dir()})

    outcome = run_case(
        Case(case.id, case.argv, case.fragments, damage_and_note), tmp_path, monkeypatch
    )
    assert outcome.code == 2, outcome.stderr_lines
    assert nodes, "the case made no node"
    assert {p: _kind(p) for p in nodes} == nodes
    assert not [p for p in tmp_path.rglob("*.tmp")]


@pytest.mark.skipif(os.geteuid() != 0, reason="mknod needs root")
def test_the_atomic_writer_never_replaces_a_device(tmp_path: Path) -> None:
    """The last line of defence, under every command: the writer itself."""
    null = tmp_path / "null"
    os.mknod(null, 0o666 | stat.S_IFCHR, os.makedev(1, 3))
    with pytest.raises(OutputError, match="null: cannot write: is a character device"):
        atomic_write_text(null, "text\n")
    assert stat.S_ISCHR(os.stat(null).st_mode)
    assert [p.name for p in tmp_path.iterdir()] == ["null"]


@pytest.mark.skipif(os.geteuid() != 0, reason="mknod needs root")
def test_a_log_file_may_be_a_character_device_written_in_place(tmp_path: Path) -> None:
    """``--log-file /dev/null`` (appended to, never replaced) is what a user expects to work."""
    null = tmp_path / "null"
    os.mknod(null, 0o666 | stat.S_IFCHR, os.makedev(1, 3))
    result = run_in_process("align", "--sim", "--log-file", str(null))
    assert result.returncode == 0, result.stderr
    assert stat.S_ISCHR(os.stat(null).st_mode)
    assert [p.name for p in tmp_path.iterdir()] == ["null"]


# -- the measurement file of a run ----------------------------------------------------------


@pytest.fixture
def short_plan(tmp_path: Path) -> Path:
    """The example plan cut to line Z with three targets: a run of a few seconds."""
    plan = read_plan(ROOT / "examples" / "plan.json")
    line = next(line for line in plan.lines if line.id == "Z")
    line.targets_mm, line.runs, line.bidirectional, line.dwell_s = (
        line.targets_mm[:3],
        1,
        True,
        0.1,
    )
    plan.lines = [line]
    path = tmp_path / "plan.json"
    write_plan(path, plan)
    return path


def _run(plan: Path, out: Path, *extra: str):
    return run_in_process(
        "run", "--sim", "--in-process", "--plan", str(plan), "--out", str(out), *extra
    )


def test_a_run_records_its_seed_and_a_resume_with_another_is_refused(
    short_plan: Path, tmp_path: Path
) -> None:
    out = tmp_path / "m.csv"
    result = _run(short_plan, out)
    assert result.returncode == 0, result.stderr
    assert load_measurements(out).sim_seed == 1
    before = out.read_bytes()
    refused = _run(short_plan, out, "--seed", "4", "--resume")
    assert refused.returncode == 2
    assert refused.stderr.strip() == (
        f"xmalign: error: --seed 4: {out} was measured on the virtual machine of --seed 1;"
        " resume it with --seed 1"
    )
    assert out.read_bytes() == before


def test_a_second_run_on_a_file_in_use_is_refused(short_plan: Path, tmp_path: Path) -> None:
    """Another process (util-linux flock(1), not xmalign) holds the file as a run would."""
    out = tmp_path / "m.csv"
    assert _run(short_plan, out).returncode == 0
    kept = len(load_measurements(out).rows)
    with out.open("a") as handle:  # a torn row: the refused resume must not cut it off
        handle.write("Z,0,+,2,1")
    before = out.read_bytes()
    holder = subprocess.Popen(["flock", "--exclusive", str(out), "sleep", "60"])
    try:
        while subprocess.run(["flock", "--nonblock", str(out), "true"]).returncode == 0:
            pass  # until the holder has it
        result = _run(short_plan, out, "--resume")
    finally:
        holder.kill()
        holder.wait()
    assert result.returncode == 2
    assert result.stderr.strip() == (
        f"xmalign: error: {out}: in use by another run (another xmalign run is writing it);"
        " wait until it ends, or give another --out"
    )
    assert out.read_bytes() == before and len(load_measurements(out, torn_ok=True).rows) == kept


def test_the_lock_lasts_the_whole_run_and_ends_with_it(tmp_path: Path) -> None:
    path = tmp_path / "new folder" / "m.csv"
    first = RunLock(path)
    with pytest.raises(InputError, match="in use by another run"):
        RunLock(path)
    assert subprocess.run(["flock", "--nonblock", str(path), "true"]).returncode != 0
    first.release()
    RunLock(path).release()
    assert subprocess.run(["flock", "--nonblock", str(path), "true"]).returncode == 0


def test_a_disk_full_during_a_run_names_the_file_and_the_points_kept(
    short_plan: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The fourth row finds the disk full after half of it is written (a torn row)."""
    out = tmp_path / "m.csv"
    real_write = os.write
    rows = []

    def write(fd: int, data: bytes | memoryview) -> int:
        if bytes(data[:2]) == b"Z,":
            rows.append(fd)
            if len(rows) == 4:
                real_write(fd, bytes(data[:10]))
                raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(fd, data)

    monkeypatch.setattr(measurements_module.os, "write", write)
    result = _run(short_plan, out)
    assert result.returncode == 2
    assert result.stderr.strip() == (
        f"xmalign: error: {out}: cannot write (disk full); 3 points kept in {out}"
    )
    recorded = load_measurements(out, torn_ok=True)
    assert len(recorded.rows) == 3 and recorded.torn is not None
    monkeypatch.setattr(measurements_module.os, "write", real_write)
    resumed = _run(short_plan, out, "--resume")
    assert resumed.returncode == 0, resumed.stderr
    points = sum(1 for line in read_plan(short_plan).lines for _ in capture_sequence(line))
    assert len(load_measurements(out).rows) == points


def test_the_measurement_writer_never_opens_a_fifo(tmp_path: Path) -> None:
    """Opening a FIFO for writing blocks until something reads it: refused first."""
    os.mkfifo(tmp_path / "ff")
    with pytest.raises(OutputError, match="ff: cannot write: is a FIFO"):
        write_measurements(tmp_path / "ff", [])


def test_a_measurement_writer_records_the_seed(tmp_path: Path) -> None:
    with MeasurementWriter.create(tmp_path / "m.csv", "ab" * 32, sim_seed=7):
        pass
    assert load_measurements(tmp_path / "m.csv").sim_seed == 7
    assert load_measurements(tmp_path / "m.csv").plan_sha256 == "ab" * 32


def test_a_plan_writer_never_writes_an_id_the_reader_refuses(tmp_path: Path) -> None:
    plan = read_plan(ROOT / "examples" / "plan.json")
    plan.lines[1].id = "Y,1"
    with pytest.raises(OutputError, match=r"lines\.1\.id.*holds ','"):
        write_plan(tmp_path / "plan.json", plan)
    assert not (tmp_path / "plan.json").exists()


# -- nothing made for bad options; all or nothing --------------------------------------------


@pytest.mark.parametrize(
    "argv",
    [
        ("dry-run", "--dialect", "nope"),
        ("dry-run", "--shop", "nowhere"),
        ("dry-run", "--stations", "2", "--verify"),
        ("mc", "--mode", "nope"),
        ("mc", "--batch", "1"),
        ("mc", "--digits", "0"),
        ("mc", "--vary", "nonsense"),
    ],
    ids=" ".join,
)
def test_bad_options_leave_no_output_folder(argv: tuple[str, ...], tmp_path: Path) -> None:
    result = run_in_process(*argv, "--out", str(tmp_path / "new"))
    assert result.returncode == 2, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert list(tmp_path.iterdir()) == []


@pytest.fixture(scope="module")
def measured(tmp_path_factory, reference_machine) -> Path:
    folder = tmp_path_factory.mktemp("measured")
    plan = six_line_plan(reference_machine, 8)
    rows = measure(
        plan,
        Chain.parse(reference_machine.chain),
        VirtualMachine(reference_machine, seed=4),
        np.random.default_rng(9),
    )
    write_plan(folder / "plan.json", plan)
    write_measurements(folder / "m.csv", rows)
    return folder


def test_a_failed_report_leaves_no_error_tables(
    measured: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The report cannot be written (its folder is a file): errors.csv is not written either."""
    (tmp_path / "afile").write_text("x\n")
    (tmp_path / "errors.csv").write_text("old tables\n")
    before = hashes(tmp_path)
    monkeypatch.chdir(tmp_path)
    result = run_in_process(
        "post",
        "--plan",
        str(measured / "plan.json"),
        "--data",
        str(measured / "m.csv"),
        "--out",
        "errors.csv",
        "--report",
        "afile/report.html",
        "--force",
    )
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        "xmalign: error: afile/report.html: cannot write: afile is a file, not a folder"
    ]
    assert hashes(tmp_path) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "errors.csv"]


def test_comp_force_replaces_and_without_it_nothing_is_written(tmp_path: Path) -> None:
    prepare(tmp_path)
    (tmp_path / "comp" / "AX_EEC.INI").write_text("; the user's own\n")
    before = hashes(tmp_path)
    refused = run_in_process(
        "comp", "--errors", str(tmp_path / "errors.csv"), "--out", str(tmp_path / "comp")
    )
    assert refused.returncode == 2 and "--force" in refused.stderr
    assert hashes(tmp_path) == before
    forced = run_in_process(
        "comp",
        "--errors",
        str(tmp_path / "errors.csv"),
        "--out",
        str(tmp_path / "comp"),
        "--force",
    )
    assert forced.returncode == 0, forced.stderr
    assert "$AA_ENC_COMP" in (tmp_path / "comp" / "AX_EEC.INI").read_text()


# -- a real full disk and a real read-only folder (root: a small tmpfs mounted for the test) --


@contextlib.contextmanager
def tmpfs(folder: Path, size: str, *options: str) -> Iterator[Path]:
    """A tmpfs of ``size`` mounted on ``folder`` (skips where mounting is not allowed)."""
    folder.mkdir()
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", ",".join([f"size={size}", *options]), "tmpfs", folder],
        capture_output=True,
    )
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {mounted.stderr.decode().strip()}")
    try:
        yield folder
    finally:
        subprocess.run(["umount", "--lazy", folder], check=True)


@pytest.mark.skipif(os.geteuid() != 0, reason="mounting a tmpfs needs root")
def test_a_run_on_a_disk_that_fills_up_keeps_every_saved_point(
    short_plan: Path, tmp_path: Path
) -> None:
    """The kernel's own ENOSPC: a 16 KiB tmpfs, 12 KiB of it taken, room for one page."""
    with tmpfs(tmp_path / "small", "16k") as small:
        (small / "filler").write_bytes(bytes(10_000))
        out = small / "m.csv"
        plan = read_plan(short_plan)
        plan.lines[0].runs = 5  # more rows than a 4 KiB page holds
        write_plan(short_plan, plan)
        result = _run(short_plan, out)
        kept = load_measurements(out, torn_ok=True)
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip() == (
        f"xmalign: error: {out}: cannot write (disk full); {len(kept.rows)} points kept in {out}"
    )
    assert len(kept.rows) > 0


@pytest.mark.skipif(os.geteuid() != 0, reason="mounting a tmpfs needs root")
def test_a_read_only_folder_keeps_the_old_file_as_root(tmp_path: Path) -> None:
    """tests/xmalign/test_bad_input.py's read-only folder, for root: a read-only mount."""
    prepare(tmp_path)
    with tmpfs(tmp_path / "locked", "64k") as locked:
        (locked / "pose.json").write_bytes((ROOT / "examples" / "pose.json").read_bytes())
        subprocess.run(["mount", "-o", "remount,ro", locked], check=True)
        result = run_in_process(
            "identify",
            "--input",
            str(tmp_path / "session.json"),
            "--out",
            str(locked / "pose.json"),
            "--force",
        )
        kept = (locked / "pose.json").read_bytes()
        left = sorted(p.name for p in locked.iterdir())
    assert result.returncode == 2
    assert result.stderr.strip() == (
        f"xmalign: error: {locked / 'pose.json'}: cannot write: read-only file system"
    )
    assert kept == (ROOT / "examples" / "pose.json").read_bytes() and left == ["pose.json"]


@pytest.mark.parametrize(
    ("stem", "size"),
    [("p" * 246, 250), ("ä" * 123, 250), ("p" * 251, 255), ("a" + "é" * 125, 255)],
    ids=["250-ascii", "250-bytes-utf8", "255-ascii", "255-utf8-cut-inside-a-character"],
)
def test_a_name_that_fits_the_file_system_is_written(tmp_path: Path, stem: str, size: int) -> None:
    """Issue 32: a valid 250-byte name was refused with "File name too long": the
    temporary file's name (``.NAME.XXXXXXXX.tmp``) was 14 bytes longer. The most a
    name may have (255 bytes) too, its temporary name cut inside a character."""
    name = f"{stem}.mpf"
    assert len(name.encode()) == size
    result = run_in_process(
        "program", "--pose", str(ROOT / "examples" / "pose.json"), "--out", str(tmp_path / name)
    )
    assert result.returncode == 0, result.stderr
    assert [p.name for p in tmp_path.iterdir()] == [name]
    assert (tmp_path / name).read_text(encoding="utf-8").strip()
