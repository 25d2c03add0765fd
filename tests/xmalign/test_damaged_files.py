"""Randomly damaged example files: every reader gives a clean XmalignError or a valid parse.

Bytes flipped, inserted, deleted or the file cut short (hypothesis): never a
traceback of another kind, whatever the damage.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from firmware_iface.config import load_units_config
from firmware_iface.interferometer import STREAM_HEADER, read_stream
from xmalign.errors import XmalignError
from xmalign.formats.error_tables import read_error_tables
from xmalign.formats.plan import read_plan
from xmalign.formats.pose import read_pose
from xmalign.formats.session import read_session
from xmalign.machine import load_machine

ROOT = Path(__file__).resolve().parents[2]

READERS: dict[str, Callable[[Path], object]] = {
    "fyxz.yaml": load_machine,
    "units.yaml": load_units_config,
    "session.json": read_session,
    "pose.json": read_pose,
    "plan.json": read_plan,
    "errors.csv": read_error_tables,
    "stream.csv": read_stream,
}
#: A recorded interferometer stream (``units.yaml``'s ``replay``), made here.
STREAM = (
    ",".join(STREAM_HEADER)
    + "\n"
    + "".join(f"{0.02 * k:.2f},{k}.5,-1.25,2.0,0.5,-3.75,12.0,1\n" for k in range(20))
)


def _original(name: str) -> bytes:
    if name == "stream.csv":
        return STREAM.encode()
    return (ROOT / "examples" / name).read_bytes()


_EDIT = st.tuples(
    st.sampled_from(["flip", "set", "insert", "delete", "cut"]),
    st.floats(0, 1, allow_nan=False),
    st.integers(0, 255),
)


def damage(data: bytes, edits: list[tuple[str, float, int]]) -> bytes:
    """Apply byte edits at relative positions: flip a bit, set, insert or delete a byte, cut."""
    buffer = bytearray(data)
    for kind, where, value in edits:
        index = min(int(where * len(buffer)), max(len(buffer) - 1, 0))
        if kind == "cut":
            del buffer[index:]
        elif not buffer:
            buffer.append(value)
        elif kind == "flip":
            buffer[index] ^= 1 << (value % 8)
        elif kind == "set":
            buffer[index] = value
        elif kind == "insert":
            buffer.insert(index, value)
        else:
            del buffer[index]
    return bytes(buffer)


def test_damage_changes_the_bytes() -> None:
    assert damage(b"abc", [("flip", 0.0, 0)]) == b"`bc"
    assert damage(b"abc", [("cut", 0.5, 0)]) == b"a"
    assert damage(b"abc", [("insert", 1.0, 65)]) == b"abAc"


@pytest.mark.parametrize("name", READERS)
def test_every_reader_survives_damage(name: str, tmp_path_factory: pytest.TempPathFactory):
    original = _original(name)
    folder = tmp_path_factory.mktemp("damaged")
    reader = READERS[name]
    (folder / name).write_bytes(original)
    reader(folder / name)  # the undamaged file is valid

    @settings(max_examples=150, deadline=None, suppress_health_check=list(HealthCheck))
    @given(edits=st.lists(_EDIT, min_size=1, max_size=4))
    def check(edits: list[tuple[str, float, int]]) -> None:
        path = folder / name
        path.write_bytes(damage(original, edits))
        try:
            reader(path)
        except XmalignError as error:
            message = str(error)
            assert "\n" not in message and str(path) in message, message

    check()
