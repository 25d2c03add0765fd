"""Gross checks on instrument data (xmalign.formats.instrument_checks) through the API.

The same damages run through the CLI in tests/xmalign/bad_input_cases.py; here
``xmalign.api.post_step`` (what a script calls) refuses them before any table
is written, and data with everything a real machine and instrument have (large
squareness, angle and scale errors, several SMR positions, a drifting material
temperature) pass.
"""

from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from sim.instrument_errors import MaterialDrift
from sim.machine import ErrorAmplitudes, VirtualMachine
from sim.tracer import VirtualTracer, measure_tracer
from sim.tracker import VirtualTracker, measure_tracker
from trajectories.instruments import tracer_points, tracker_points
from xmalign import api
from xmalign.errors import InputError
from xmalign.formats.instrument_checks import check_instrument_files
from xmalign.formats.instruments import (
    TracerFile,
    TrackerFile,
    read_tracer_lengths,
    read_tracker_points,
    write_tracker_points,
)
from xmalign.post.evaluate import Instruments

ROOT = Path(__file__).resolve().parents[2]


def _post(machine, tmp_path: Path, trackers=(), tracers=()) -> None:
    api.post_step(
        machine,
        [],
        tmp_path / "errors.csv",
        instruments=Instruments(tuple(trackers), tuple(tracers)),
    )


def test_a_tracker_file_in_inches_is_refused_before_any_table(reference_machine, tmp_path) -> None:
    example = read_tracker_points(ROOT / "examples" / "tracker.csv")
    inches = [replace(p, tracker_mm=p.tracker_mm / 25.4) for p in example.points]
    write_tracker_points(tmp_path / "inches.csv", inches)
    with pytest.raises(InputError, match=r"inches.csv: line 4: .* in inches, not mm"):
        _post(reference_machine, tmp_path, [read_tracker_points(tmp_path / "inches.csv")])
    assert not (tmp_path / "errors.csv").exists()


def test_the_same_file_a_link_or_a_copy_is_refused(reference_machine, tmp_path) -> None:
    shutil.copy(ROOT / "examples" / "tracer.csv", tmp_path / "a.csv")
    shutil.copy(tmp_path / "a.csv", tmp_path / "copy.csv")
    (tmp_path / "link.csv").symlink_to(tmp_path / "a.csv")
    first = read_tracer_lengths(tmp_path / "a.csv")
    for other, what in (
        ("a.csv", "the same file"),
        ("link.csv", "the same file"),
        ("copy.csv", "the same readings"),
    ):
        with pytest.raises(InputError, match=f"{other}: .*{what}"):
            _post(
                reference_machine, tmp_path, tracers=[first, read_tracer_lengths(tmp_path / other)]
            )


def test_rows_built_in_memory_are_named_by_row(reference_machine) -> None:
    example = read_tracker_points(ROOT / "examples" / "tracker.csv")
    points = list(example.points)
    points[7] = replace(points[7], machine_mm=points[7].machine_mm + [0.0, 3000.0, 0.0])
    with pytest.raises(InputError, match=r"mine: row 8: the commanded point .* 1\d\d\d mm outside"):
        check_instrument_files(reference_machine, [TrackerFile(points, "mine")], [])


def test_a_wrong_tracer_length_is_named_and_the_good_ones_pass(reference_machine) -> None:
    example = read_tracer_lengths(ROOT / "examples" / "tracer.csv")
    check_instrument_files(reference_machine, [], [example])
    lengths = list(example.lengths)
    lengths[300] = replace(lengths[300], length_mm=lengths[300].length_mm + 25.0)
    damaged = TracerFile(lengths, "t.csv", lines=example.lines)
    with pytest.raises(
        InputError, match=rf"t.csv: line {example.lines[300]}: this length lies 25 mm"
    ):
        check_instrument_files(reference_machine, [], [damaged])


def test_real_machines_and_instruments_pass_the_checks(reference_machine) -> None:
    """Large squareness (seed 004: 2900 urad), big amplitudes, systematic errors, SMRs, drift."""
    offsets = {"A": np.array([0.0, 0.0, -100.0]), "B": np.array([120.0, 0.0, -60.0])}
    machine = reference_machine.model_copy(update={"smr_offsets_mm": offsets})
    amplitudes = ErrorAmplitudes(squareness_urad=2900.0)
    truth = VirtualMachine(machine, amplitudes, seed=3)
    drift = MaterialDrift(22.0, 24.0, 11.5)
    tracker = VirtualTracker(np.array([1000.0, 750.0, -900.0]), np.array([0.5, -1.0, 30.0]), seed=2)
    rows = measure_tracker(
        truth, tracker, tracker_points(machine), 1, machine.smr_offset,
        angle_systematic_urad=20.0, scale_ppm=2.0, smr_offsets_mm=offsets, material=drift,
    )  # fmt: skip
    lengths = measure_tracer(
        truth, VirtualTracer(np.array([200.0, 150.0, -650.0]), seed=4), tracer_points(machine), 1,
        machine.smr_offset, scale_ppm=1.0, smr_offsets_mm=offsets, material=drift,
    )  # fmt: skip
    check_instrument_files(machine, [TrackerFile(rows, "t")], [TracerFile(lengths, "r")])
