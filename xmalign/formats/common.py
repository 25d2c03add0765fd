"""Shared reading and writing helpers for xmalign's files."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ValidationError

from xmalign.errors import FormatError, InputError

M = TypeVar("M", bound=BaseModel)


def describe_validation_error(error: ValidationError, source: str) -> str:
    """One line naming the file, the first offending key and what is wrong with it."""
    first = error.errors()[0]
    key = ".".join(str(part) for part in first["loc"]) or "(top level)"
    if first["type"] == "missing":
        return f"{source}: missing key '{key}'"
    if first["type"] == "extra_forbidden":
        return f"{source}: unknown key '{key}'"
    message = first["msg"].removeprefix("Value error, ")
    return f"{source}: key '{key}': {message}"


def validate(model: type[M], data: object, source: str) -> M:
    """``model.model_validate(data)`` with an InputError naming ``source`` and the key."""
    try:
        return model.model_validate(data)
    except ValidationError as error:
        raise InputError(describe_validation_error(error, source)) from error


def read_yaml(path: str | Path, what: str = "file") -> object:
    """Parse a YAML file; errors name the file (and the line of a syntax error)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as error:
        raise InputError(f"{path}: cannot read {what} ({error.strerror})") from error
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as error:
        mark = getattr(error, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise InputError(f"{path}: not valid YAML{where}") from error


def read_json(path: str | Path, expected_format: str) -> dict[str, Any]:
    """Read a JSON file and check its ``format`` key (``name/version``).

    Raises
    ------
    InputError
        The file is missing or not JSON (with line and column).
    FormatError
        The format name or version is not ``expected_format``.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as error:
        raise InputError(f"{path}: cannot read ({error.strerror})") from error
    try:
        data = json.loads(text)
    except json.JSONDecodeError as error:
        raise InputError(
            f"{path}: not valid JSON at line {error.lineno} column {error.colno}: {error.msg}"
        ) from error
    if not isinstance(data, dict):
        raise FormatError(f"{path}: expected a JSON object with a 'format' key")
    check_format(data.get("format"), expected_format, str(path))
    return data


def check_format(found: object, expected_format: str, source: str) -> None:
    """Refuse a missing, foreign or newer ``format`` value with a clear message."""
    name, _, version = expected_format.partition("/")
    if found is None:
        raise FormatError(f"{source}: missing key 'format' (expected '{expected_format}')")
    found_name, _, found_version = str(found).partition("/")
    if found_name != name:
        raise FormatError(f"{source}: format '{found}' is not a {name} file")
    if found_version != version:
        raise FormatError(
            f"{source}: format version '{found_version}' of {name} is not supported"
            f" (this xmalign reads version {version})"
        )


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write ``text`` so that a reader never sees half a file (temp file + rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as handle:
            handle.write(text)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_json(path: str | Path, data: dict[str, Any]) -> None:
    """Write a JSON document atomically, indented for people."""
    atomic_write_text(path, json.dumps(data, indent=2) + "\n")
