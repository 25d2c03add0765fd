"""Where a file came from: format and version, software, time, and its inputs' SHA-256.

Every file xmalign writes carries its history (docs/formats.md, "Versions and
history"), written and read here and nowhere else:

- JSON files get the keys ``format`` (``name/version``), ``software``
  (``xmalign 0.1.0``), ``created_utc`` (ISO 8601, seconds, ``Z``) and
  ``inputs``: one ``{"role", "path", "sha256"}`` per file it was made from;
- CSV files get a preamble of ``#`` comment lines before their header::

      # format: xmalign.error-tables/2
      # software: xmalign 0.1.0
      # created_utc: 2026-11-26T01:02:03Z
      # input measurements: 9f86d081...  m.csv

  an ``input`` line ends with exactly what ``sha256sum FILE`` prints, so anyone
  can check the chain without xmalign (a name with a backslash, a line feed or a
  carriage return is escaped as ``sha256sum`` escapes it: ``\\HEX  a\\nb``; a
  name with another character that ends a line is refused); other
  ``# key: value`` lines carry what a format adds (the error table's ``machine``);
- other formats write the same lines (:func:`history_lines`) in their own comment
  syntax (G-code, controller files), and a format that takes no comment gets
  ``NAME.history`` beside it (:func:`history_file`), which ``sha256sum -c`` checks.

The SHA-256 is that of the file's bytes. A reader accepts every version up to
the one it knows (``common.check_format``) and refuses a newer one with one line.
"""

from __future__ import annotations

import hashlib
import json
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from xmalign import __version__
from xmalign.errors import InputError
from xmalign.formats.common import check_format, located, os_problem

SOFTWARE = f"xmalign {__version__}"
#: The JSON keys of a file's history (besides ``format``).
HISTORY_KEYS = ("software", "created_utc", "inputs")
_INPUT_LINE = re.compile(
    r"^input (?P<role>[\w.-]+): (?P<escaped>\\?)(?P<sha256>[0-9a-f]{64})  (?P<path>.+)$"
)
#: How ``sha256sum`` escapes a file name in its line (GNU coreutils 9).
_SHA256SUM_ESCAPES = {"\\": "\\\\", "\n": "\\n", "\r": "\\r"}
_SHA256SUM_UNESCAPES = re.compile(r"\\(.)")
#: Characters that end a line for Python's ``str.splitlines`` besides the escaped ones.
_OTHER_LINE_ENDS = frozenset("\v\f\x1c\x1d\x1e\x85\u2028\u2029")


@dataclass(frozen=True)
class FileSource:
    """A file something was made from: its role (``plan``), path and SHA-256 (hex)."""

    role: str
    path: str
    sha256: str

    @classmethod
    def of(cls, role: str, path: str | Path) -> FileSource:
        """The source as the file is now (its bytes hashed).

        Raises
        ------
        InputError
            The file cannot be read.
        """
        ends = sorted(_OTHER_LINE_ENDS.intersection(str(path)))
        if ends:
            raise InputError(
                located(
                    repr(str(path)),
                    "file name",
                    f"holds {ends[0]!r}, which ends a line of the files' history; rename the file",
                )
            )
        return cls(role, str(path), file_sha256(path))

    def sha256sum_line(self) -> str:
        """The line ``sha256sum`` prints for the file: ``HEX  PATH``, or ``\\HEX  PATH`` with
        the backslashes, line feeds and carriage returns of the name escaped."""
        if not any(char in self.path for char in _SHA256SUM_ESCAPES):
            return f"{self.sha256}  {self.path}"
        escaped = "".join(_SHA256SUM_ESCAPES.get(char, char) for char in self.path)
        return f"\\{self.sha256}  {escaped}"


@dataclass(frozen=True)
class Provenance:
    """The history a file carries; ``version`` 1 files written before it have none."""

    format: str
    software: str | None = None
    created_utc: str | None = None
    inputs: tuple[FileSource, ...] = ()
    extra: Mapping[str, str] = field(default_factory=dict)

    @property
    def version(self) -> int:
        return int(self.format.rpartition("/")[2])

    def input(self, role: str) -> FileSource | None:
        """The first input of ``role``, or None."""
        return next((source for source in self.inputs if source.role == role), None)


def file_sha256(path: str | Path) -> str:
    """SHA-256 of a file's bytes, hex (what ``sha256sum`` prints)."""
    digest = hashlib.sha256()
    try:
        with Path(path).open("rb") as handle:
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
    except OSError as error:
        raise InputError(located(path, "cannot read", os_problem(error))) from error
    return digest.hexdigest()


def now_utc() -> str:
    """The present UTC time, ISO 8601 to the second (``2026-11-26T01:02:03Z``)."""
    return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def sources(**paths: str | Path | None) -> list[FileSource]:
    """``FileSource`` of every named path that is given (``plan=..., machine=None``)."""
    return [FileSource.of(role, path) for role, path in paths.items() if path is not None]


def json_history(format_name: str, inputs: Iterable[FileSource] = ()) -> dict[str, Any]:
    """The keys a JSON file starts with: ``format``, ``software``, ``created_utc``, ``inputs``."""
    return {
        "format": format_name,
        "software": SOFTWARE,
        "created_utc": now_utc(),
        "inputs": [{"role": s.role, "path": s.path, "sha256": s.sha256} for s in inputs],
    }


def read_json_history(data: Mapping[str, Any], source: str) -> Provenance:
    """The history of a decoded JSON file (format already checked); keys absent in /1 files."""
    inputs: list[FileSource] = []
    for index, item in enumerate(data.get("inputs") or []):
        try:
            inputs.append(FileSource(str(item["role"]), str(item["path"]), str(item["sha256"])))
        except (KeyError, TypeError) as error:
            raise InputError(
                located(source, f"key 'inputs.{index}'", "needs role, path and sha256")
            ) from error
    return Provenance(
        format=str(data["format"]),
        software=data.get("software"),
        created_utc=data.get("created_utc"),
        inputs=tuple(inputs),
    )


def without_history(data: Mapping[str, Any]) -> dict[str, Any]:
    """A decoded JSON document without its history keys (what the content is)."""
    return {key: value for key, value in data.items() if key not in HISTORY_KEYS}


def history_lines(
    format_name: str, inputs: Iterable[FileSource] = (), extra: Mapping[str, str] | None = None
) -> list[str]:
    """A file's history as ``key: value`` lines, without a comment mark: ``format``,
    ``software``, ``created_utc``, one ``input ROLE: HEX  PATH`` per input (what
    ``sha256sum`` prints) and the ``extra`` keys. Every format writes these lines in its
    own comment syntax (:func:`csv_preamble`; G-code and controller files)."""
    return [
        f"format: {format_name}",
        f"software: {SOFTWARE}",
        f"created_utc: {now_utc()}",
        *(f"input {s.role}: {s.sha256sum_line()}" for s in inputs),
        *(f"{key}: {value}" for key, value in (extra or {}).items()),
    ]


def csv_preamble(
    format_name: str, inputs: Iterable[FileSource] = (), extra: Mapping[str, str] | None = None
) -> str:
    """The ``#`` lines a CSV file starts with (each ends with a line end)."""
    return "".join(f"# {line}\n" for line in history_lines(format_name, inputs, extra))


def history_path(path: Path) -> Path:
    """Where the history of a file whose format takes no comment goes: ``NAME.history``
    beside it (:func:`history_file`)."""
    return path.with_name(f"{path.name}.history")


def history_file(format_name: str, name: str, data: bytes, inputs: Iterable[FileSource]) -> str:
    """``NAME.history``: the history of a file whose format takes no comment, beside it.

    The ``#`` lines of :func:`csv_preamble` (with ``file: NAME``), then the file's own
    ``sha256sum`` line: ``sha256sum -c NAME.history`` in its folder checks the file (it
    skips the ``#`` lines), and the ``# input`` lines, without their ``# input ROLE:``,
    check the inputs the same way.
    """
    preamble = csv_preamble(format_name, inputs, {"file": name})
    return preamble + f"{hashlib.sha256(data).hexdigest()}  {name}\n"


def read_csv_preamble(
    comments: Iterable[str], expected_format: str, source: str, first_format: str
) -> Provenance:
    """The history in a CSV file's leading ``#`` lines (the ``#`` included).

    A file without a ``# format:`` line is ``first_format`` (version 1, written
    before files carried their history). A newer version is refused.
    """
    values: dict[str, str] = {}
    inputs: list[FileSource] = []
    for text in comments:
        key, separator, value = text.lstrip("#").strip().partition(": ")
        match = _INPUT_LINE.match(text.lstrip("#").strip())
        if match:
            path = match["path"]
            if match["escaped"]:
                path = _SHA256SUM_UNESCAPES.sub(lambda m: _unescape(m[1]), path)
            inputs.append(FileSource(match["role"], path, match["sha256"]))
        elif separator and " " not in key:
            values.setdefault(key, value.strip())
    format_name = values.pop("format", first_format)
    check_format(format_name, expected_format, source)
    return Provenance(
        format=format_name,
        software=values.pop("software", None),
        created_utc=values.pop("created_utc", None),
        inputs=tuple(inputs),
        extra=values,
    )


def _unescape(char: str) -> str:
    return {"n": "\n", "r": "\r"}.get(char, char)


def json_value(provenance: Provenance, key: str, source: str) -> Any:
    """A preamble value written as JSON (the error table's ``machine``), or None."""
    text = provenance.extra.get(key)
    if text is None:
        return None
    try:
        return json.loads(text)
    except json.JSONDecodeError as error:
        raise InputError(located(source, f"'# {key}' line", "not valid JSON")) from error
