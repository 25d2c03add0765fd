"""Reading, validating and writing xmalign's files: the one layer every format goes through.

Readers get their text from :func:`read_text` (a missing file, a folder, no
permission or bytes that are not UTF-8 become one line naming the file),
their data from :func:`read_json` or :func:`read_yaml` (duplicate keys and
non-finite numbers refused, naming the key) and validate it with a pydantic
model through :func:`validate`. Every message has the shape ``FILE: WHERE:
PROBLEM`` (:func:`located`), WHERE being a key or a line.

Writers go through :func:`atomic_write_bytes`: a temporary file in the same
folder, fsync, then ``os.replace``, with the mode a plain ``open`` would give
(``0666 & ~umask``). A failed write leaves the old file as it was, and a path
that is not a regular file (a device such as ``/dev/null``, a FIFO, a socket)
is never replaced. Commands check their outputs first, before any work, with
:func:`refuse_overwriting` (an output that is one of the inputs or another
output, or not a regular file) and :func:`refuse_replacing` (an existing file
replaced only when the user says ``--force``); see docs/formats.md, "Outputs".

The bounds below are what a real machine and instrument can have; a value
outside them is a typing or unit mistake, refused before it reaches a
controller (docs/formats.md, "Validation").
"""

from __future__ import annotations

import contextlib
import errno
import json
import math
import os
import re
import stat
import tempfile
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Annotated, Any, TypeVar, get_args

import numpy as np
import yaml
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, SecretStr, ValidationError
from pydantic.fields import FieldInfo

from xmalign.errors import FormatError, InputError, OutputError

#: Largest travel, position or distance, mm (100 m).
MAX_LENGTH_MM = 100_000.0
#: Largest angle an encoder or a file may report, degrees (two turns either way).
MAX_ANGLE_DEG = 720.0
#: Largest translation error in an error table, mm (1 mm).
MAX_ERROR_MM = 1.0
#: Largest rotation or squareness error in an error table, rad (10 mrad).
MAX_ERROR_RAD = 0.01

Finite = Annotated[float, Field(allow_inf_nan=False)]
Length_mm = Annotated[float, Field(ge=-MAX_LENGTH_MM, le=MAX_LENGTH_MM, allow_inf_nan=False)]
Distance_mm = Annotated[float, Field(gt=0, le=MAX_LENGTH_MM, allow_inf_nan=False)]
Angle_deg = Annotated[float, Field(ge=-MAX_ANGLE_DEG, le=MAX_ANGLE_DEG, allow_inf_nan=False)]
Vector3_mm = Annotated[list[Length_mm], Field(min_length=3, max_length=3)]

M = TypeVar("M", bound=BaseModel)


class FileModel(BaseModel):
    """Base of the models of xmalign's files: finite numbers only."""

    model_config = ConfigDict(allow_inf_nan=False)


class StrictFileModel(FileModel):
    """A file model that refuses keys it does not know (YAML written by people)."""

    model_config = ConfigDict(allow_inf_nan=False, extra="forbid", frozen=True)


def _secret_text(value: object) -> object:
    """A password as text: a whole number as written (YAML ``4711`` is the password
    ``4711``); a yes/no value or a decimal number refused (YAML may have changed them)."""
    if isinstance(value, bool | float):
        raise ValueError("not text: write the password in quotes")
    return str(value) if isinstance(value, int) else value


#: A password or other secret in a file: text (a whole number is taken as written),
#: shown as ``**********``, and never shown in an error message (:func:`validate`).
Secret = Annotated[SecretStr, BeforeValidator(_secret_text)]


def is_secret_field(field: FieldInfo) -> bool:
    """A field whose value is never shown: a SecretStr (or one inside an Optional,
    Annotated ...), or a field marked ``Field(json_schema_extra={"secret": True})``."""
    extra = field.json_schema_extra
    return (isinstance(extra, dict) and extra.get("secret") is True) or _mentions(
        field.annotation, SecretStr
    )


def _mentions(annotation: object, wanted: type) -> bool:
    if annotation is wanted:
        return True
    return any(_mentions(argument, wanted) for argument in get_args(annotation))


def _models_in(annotation: object) -> list[type[BaseModel]]:
    """The models an annotation can hold (itself, or inside Optional, Union, list, dict...)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [model for argument in get_args(annotation) for model in _models_in(argument)]


def secret_at(model: type[BaseModel], loc: Sequence[int | str]) -> bool:
    """Whether the key at ``loc`` (a ValidationError's) is, or lies inside, a secret field.

    Parts that name no field (a union's tag, a list index, a dict key) are stepped over.
    """
    models = [model]
    for part in loc:
        fields = [
            m.model_fields[part] for m in models if isinstance(part, str) and part in m.model_fields
        ]
        if not fields:
            continue
        if any(is_secret_field(field) for field in fields):
            return True
        models = [found for field in fields for found in _models_in(field.annotation)]
    return False


def shown_value(value: object) -> str:
    """A value as a one-line message shows it: its repr when short, else its type."""
    text = repr(value)
    return text if len(text) <= 60 and "\n" not in text else f"a {type(value).__name__}"


def path_argument(value: object, name: str, what: str = "a file's path") -> Path:
    """``value`` as a Path when it is a non-empty ``str`` or ``os.PathLike``; else one
    InputError naming the argument ``name`` (a script's number or None, not a TypeError)."""
    if isinstance(value, str | os.PathLike) and str(value) != "":
        return Path(value)
    raise InputError(f"{name}: {shown_value(value)} is not {what} (give a str or a Path)")


def located(source: str | Path, where: str, problem: str) -> str:
    """The one shape of every file error: ``FILE: WHERE: PROBLEM`` (WHERE: a key or a line)."""
    return f"{source}: {where}: {problem}"


def key_error(source: str | Path, key: str, problem: str) -> InputError:
    """An InputError naming the file and the key."""
    return InputError(located(source, f"key '{key}'", problem))


def line_error(source: str | Path, line: int, problem: str) -> InputError:
    """An InputError naming the file and the line (1-based)."""
    return InputError(located(source, f"line {line}", problem))


#: What a path is whose symbolic links lead back to themselves.
LOOP = "a symbolic link that loops (it leads back to itself)"

_OS_PROBLEMS = {
    errno.ENOENT: "no such file",
    errno.EISDIR: "is a folder, not a file",
    errno.ENOTDIR: "a part of the path is not a folder",
    errno.EACCES: "permission denied",
    errno.EPERM: "permission denied",
    errno.EROFS: "read-only file system",
    errno.ENOSPC: "disk full",
    errno.EDQUOT: "disk quota exceeded",
    errno.EEXIST: "exists",
    errno.ELOOP: LOOP,
}


def os_problem(error: OSError) -> str:
    """A short reason for an OSError (no errno numbers, no Python words)."""
    return _OS_PROBLEMS.get(error.errno or -1) or error.strerror or str(error)


def read_text(path: str | Path) -> str:
    """The UTF-8 text of a file (a leading byte-order mark is dropped).

    Raises
    ------
    InputError
        The file is missing, a folder, unreadable, or not UTF-8 (naming the line).
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as error:
        raise InputError(located(path, "cannot read", os_problem(error))) from error
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as error:
        line = data[: error.start].count(b"\n") + 1
        raise line_error(path, line, f"byte 0x{data[error.start]:02x} is not UTF-8 text") from error


def _walk_finite(data: object, source: str, key: str) -> None:
    if isinstance(data, float) and not math.isfinite(data):
        raise key_error(source, key or "(top level)", f"{data} is not a finite number")
    if isinstance(data, dict):
        for name, value in data.items():
            _walk_finite(value, source, f"{key}.{name}" if key else str(name))
    elif isinstance(data, list):
        for index, value in enumerate(data):
            _walk_finite(value, source, f"{key}.{index}" if key else str(index))


def check_finite(data: object, source: str) -> None:
    """Refuse NaN and Infinity anywhere in a decoded document, naming the key."""
    _walk_finite(data, source, "")


def describe_problem(first: Any, secret: bool = False) -> str:
    """What is wrong, in words, for one entry of ``ValidationError.errors()``;
    ``secret``: the key holds a password, whose value is never shown."""
    kind = first["type"]
    if kind == "missing":
        return "missing"
    if kind == "extra_forbidden":
        return "not a known key"
    if kind == "finite_number":
        return f"{'the value' if secret else first['input']} is not a finite number"
    if kind in ("too_short", "too_long"):
        context = first.get("ctx", {})
        bound = "at least" if kind == "too_short" else "at most"
        count = context.get("min_length" if kind == "too_short" else "max_length")
        return f"must have {bound} {count} values, not {context.get('actual_length')}"
    message = first["msg"].removeprefix("Value error, ").removeprefix("Assertion failed, ")
    if message.startswith("Input should be"):
        value = first.get("input")
        shown = f"{value!r} " if isinstance(value, int | float | str) and not secret else ""
        message = shown + message.replace("Input should be", "must be", 1)
    return message


def describe_validation_error(error: ValidationError, source: str, secret: bool = False) -> str:
    """One line naming the file, the first offending key and what is wrong with it
    (``secret``: the key holds a password, whose value is never shown)."""
    first = error.errors()[0]
    key = ".".join(str(part) for part in first["loc"]) or "(top level)"
    return located(source, f"key '{key}'", describe_problem(first, secret))


def _yes_no_read_as_number(value: object, raw: object, key: str) -> str | None:
    """The key of the first ``true``/``false`` in ``raw`` that validated into a number."""
    if isinstance(raw, bool):
        return None if isinstance(value, bool) else key
    pairs: Iterable[tuple[object, object, object]] = ()
    if isinstance(value, BaseModel) and isinstance(raw, dict):
        pairs = (
            (field.alias or name, getattr(value, name), raw.get(field.alias or name))
            for name, field in type(value).model_fields.items()
        )
    elif isinstance(value, dict) and isinstance(raw, dict):
        pairs = ((name, value.get(name), item) for name, item in raw.items())
    elif isinstance(raw, list) and isinstance(value, list | tuple | np.ndarray):
        pairs = ((index, *pair) for index, pair in enumerate(zip(value, raw, strict=False)))
    for name, item, raw_item in pairs:
        found = _yes_no_read_as_number(item, raw_item, f"{key}.{name}" if key else str(name))
        if found is not None:
            return found
    return None


def validate(model: type[M], data: object, source: str, context: dict | None = None) -> M:
    """``model.model_validate(data)`` with an InputError naming ``source`` and the key.

    A yes/no value (JSON ``true``, YAML ``yes``) where a number is expected is refused:
    pydantic would read it as 1.0.
    """
    check_finite(data, source)
    try:
        validated = model.model_validate(data, context=context)
    except ValidationError as error:
        secret = secret_at(model, error.errors()[0]["loc"])
        message = describe_validation_error(error, source, secret)
        if secret:
            # pydantic's own message (the cause) carries the input: not even a traceback shows it
            raise InputError(message) from None
        raise InputError(message) from error
    key = _yes_no_read_as_number(validated, data, "")
    if key is not None:
        raise key_error(
            source, key, "a yes/no value (true/false, yes/no) where a number is expected"
        )
    return validated


class _UniqueKeyLoader(yaml.SafeLoader):
    """A SafeLoader that refuses a key given twice in one mapping."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen: dict[object, int] = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            try:
                first = seen.get(key)
            except TypeError:  # unhashable: SafeLoader itself explains it
                continue
            if first is not None:
                raise yaml.constructor.ConstructorError(
                    None,
                    None,
                    f"key '{key}' given twice (first on line {first})",
                    key_node.start_mark,
                )
            seen[key] = key_node.start_mark.line + 1
        return super().construct_mapping(node, deep=deep)


#: Most values a YAML document may hold once its aliases are expanded: far more than
#: any xmalign file, far fewer than an alias bomb (``a: &a [x, x, ...]``, ``b: [*a, *a, ...]``).
MAX_YAML_VALUES = 100_000

#: Unquoted numbers that YAML 1.1 (PyYAML) reads other than a person means: a leading
#: zero is octal (``010`` is 8, ``-0500`` is -320), colons are base 60 (``1:30`` is 90).
#: YAML 1.2 reads both as text; xmalign refuses them (docs/formats.md, "YAML numbers").
_YAML_1_1_NUMBERS = (
    (
        re.compile(r"[-+]?0[0-9_]+"),
        "a number with a leading zero (YAML 1.1 reads it as octal): drop the zero",
    ),
    (
        re.compile(r"[-+]?[0-9][0-9_]*(:[0-5]?[0-9])+(\.[0-9_]*)?"),
        "a number with a colon (YAML 1.1 reads it in base 60): write it in one unit",
    ),
)


def _yaml_number_problem(node: yaml.Node) -> str | None:
    """Why an unquoted scalar is refused as a number, or None."""
    if not isinstance(node, yaml.ScalarNode) or node.style is not None:
        return None
    for pattern, problem in _YAML_1_1_NUMBERS:
        if pattern.fullmatch(node.value):
            return problem + ", or quote it if it is text"
    return None


def _check_yaml_nodes(root: yaml.Node, path: Path) -> None:
    """Refuse YAML 1.1 numbers (naming line and key) and aliases that expand without bound.

    Walks the node tree as the data will be walked, aliases expanded, and stops
    once :data:`MAX_YAML_VALUES` values have been seen.
    """
    stack: list[tuple[yaml.Node, str]] = [(root, "")]
    seen = 0
    while stack:
        node, key = stack.pop()
        seen += 1
        if seen > MAX_YAML_VALUES:
            raise InputError(
                located(
                    path,
                    "not valid YAML",
                    f"its aliases expand to more than {MAX_YAML_VALUES} values",
                )
            )
        problem = _yaml_number_problem(node)
        if problem is not None:
            where = f"key '{key or '(top level)'}' (line {node.start_mark.line + 1})"
            raise InputError(located(path, where, problem))
        if isinstance(node, yaml.MappingNode):
            for key_node, value_node in node.value:
                name = key_node.value if isinstance(key_node, yaml.ScalarNode) else "?"
                stack.append((key_node, key))
                stack.append((value_node, f"{key}.{name}" if key else str(name)))
        elif isinstance(node, yaml.SequenceNode):
            stack += [(item, f"{key}.{i}" if key else str(i)) for i, item in enumerate(node.value)]


def _load_yaml(text: str, path: Path) -> object:
    loader = _UniqueKeyLoader(text)
    try:
        root = loader.get_single_node()
        if root is None:
            return None
        _check_yaml_nodes(root, path)
        return loader.construct_document(root)
    finally:
        loader.dispose()


def read_yaml(path: str | Path) -> object:
    """Parse a YAML file; errors name the file and the line.

    Refused, besides syntax errors: a key given twice, an unquoted number that
    YAML 1.1 would change (``010``, ``1:30``; see :data:`_YAML_1_1_NUMBERS`) and
    aliases that expand to more than :data:`MAX_YAML_VALUES` values.
    """
    path = Path(path)
    text = read_text(path)
    try:
        data = _load_yaml(text, path)
    except yaml.MarkedYAMLError as error:
        mark = error.problem_mark or error.context_mark
        where = f"line {mark.line + 1}" if mark is not None else "not valid YAML"
        problem = error.problem if "given twice" in (error.problem or "") else None
        raise InputError(
            located(path, where, problem or f"not valid YAML ({error.problem or error.context})")
        ) from error
    except RecursionError as error:
        raise InputError(located(path, "not valid YAML", "nested too deeply")) from error
    except InputError:
        raise
    except (yaml.YAMLError, ValueError) as error:  # e.g. a date like 2024-13-45
        raise InputError(located(path, "not valid YAML", str(error).splitlines()[0])) from error
    return data


class _DuplicateKeyError(ValueError):
    def __init__(self, key: str) -> None:
        super().__init__(key)
        self.key = key


def _unique_pairs(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    result: dict[str, Any] = {}
    for key, value in pairs:
        if key in result:
            raise _DuplicateKeyError(key)
        result[key] = value
    return result


def read_json(path: str | Path, expected_format: str) -> dict[str, Any]:
    """Read a JSON file and check its ``format`` key (``name/version``).

    Raises
    ------
    InputError
        The file cannot be read, is not JSON (with line and column), repeats a
        key or holds a non-finite number.
    FormatError
        Not the format of ``expected_format`` or a newer version of it.
    """
    path = Path(path)
    text = read_text(path)
    try:
        data = json.loads(text, object_pairs_hook=_unique_pairs)
    except _DuplicateKeyError as error:
        raise key_error(path, error.key, "given twice") from error
    except json.JSONDecodeError as error:
        raise line_error(
            path, error.lineno, f"not valid JSON at column {error.colno}: {error.msg}"
        ) from error
    except RecursionError as error:
        raise InputError(located(path, "not valid JSON", "nested too deeply")) from error
    except ValueError as error:  # e.g. an integer of thousands of digits
        problem = "a number has too many digits" if "digits" in str(error) else str(error)
        raise InputError(located(path, "not valid JSON", problem)) from error
    if not isinstance(data, dict):
        raise FormatError(located(path, "top level", "expected a JSON object with a 'format' key"))
    check_format(data.get("format"), expected_format, str(path))
    return data


def format_problem(found: str, expected_format: str) -> str | None:
    """What keeps a reader of ``expected_format`` (``name/N``) from reading ``found``.

    Versions 1 to N are read (each reader migrates the older ones); a foreign
    name, a version that is not a whole number or a newer one is a problem.
    """
    name, _, newest = expected_format.partition("/")
    found_name, _, found_version = found.partition("/")
    if found_name != name:
        return f"'{found}' is not a {name} file"
    if not found_version.isdigit() or int(found_version) < 1:
        return f"'{found}': the version is not a whole number"
    if int(found_version) > int(newest):
        return f"written by a newer xmalign: format {found}, this one reads up to /{newest}"
    return None


def check_format(found: object, expected_format: str, source: str) -> int:
    """The version of a ``format`` value; refuse a missing, foreign or newer one
    (:func:`format_problem`) with one line naming the file."""
    if found is None:
        raise FormatError(
            located(source, "key 'format'", f"missing (expected '{expected_format}')")
        )
    problem = format_problem(str(found), expected_format)
    if problem is not None:
        raise FormatError(located(source, "key 'format'", problem))
    return int(str(found).partition("/")[2])


def _new_file_mode() -> int:
    """``0666 & ~umask``: the mode ``open(path, "w")`` would give a new file."""
    mask = os.umask(0o022)
    os.umask(mask)
    return 0o666 & ~mask


def sync_folder(folder: Path) -> None:
    """Make a new file's name durable too (not every file system can sync a folder)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass  # some file systems cannot sync a folder; the rename is done all the same
    finally:
        os.close(fd)


#: Paths given to one option: none, one, or several (a repeated option).
PathsOf = Path | Sequence[Path] | None

_KINDS = (
    (stat.S_ISDIR, "a folder"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISSOCK, "a socket"),
)


def special_kind(path: Path) -> str | None:
    """What ``path`` is when it exists and is not a regular file ("a character device"...).

    Links are followed: a link to ``/dev/null`` is a character device; links that lead
    back to themselves are :data:`LOOP`.
    """
    try:
        mode = os.stat(path).st_mode
    except OSError as error:
        return LOOP if error.errno == errno.ELOOP else None
    return next((kind for test, kind in _KINDS if test(mode)), None)


def refuse_special(path: Path, where: str, appended: bool = False) -> None:
    """Refuse an output that exists and is not a regular file (``where``: the option).

    ``appended`` (a log): a character device such as ``/dev/null`` or
    ``/dev/stderr`` is written to in place, as a shell's ``>>`` would; it is
    never replaced. A FIFO would block the command until something reads it.

    Raises
    ------
    OutputError
        Naming the file, ``where`` and what the path is.
    """
    kind = special_kind(path)
    if kind is None or (appended and kind == "a character device"):
        return
    if kind == "a folder":
        raise OutputError(located(path, where, "is a folder; give a file name"))
    if kind == LOOP:
        raise OutputError(located(path, where, f"is {LOOP}; give a file name"))
    raise OutputError(
        located(
            path,
            where,
            f"is {kind}, not a regular file; xmalign writes its files only as regular"
            " files (give a file name)",
        )
    )


def _each(paths: PathsOf) -> Iterable[Path]:
    if paths is None:
        return ()
    if isinstance(paths, Path | str):
        return (Path(paths),)
    return (Path(p) for p in paths)


def same_file(a: Path, b: Path) -> bool:
    """True when two paths name one file: the same device and inode, links followed; a
    missing file (a dangling link's target) by its full path. Never raises (a loop is
    compared by its path)."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return link_target(a) == link_target(b)


def link_target(path: Path) -> Path:
    """The file ``path`` names once its symbolic links are followed (the full path; a
    dangling link's target; a loop as far as it can be followed)."""
    return Path(os.path.realpath(path))


def check_output_folder(path: Path, option: str) -> None:
    """Refuse a file in the place of an output folder (nothing is created yet).

    Raises
    ------
    InputError
        ``path`` is an existing file.
    """
    if path.exists() and not path.is_dir():
        raise InputError(located(path, option, "is a file; give a folder for the output files"))


def refuse_overwriting(
    inputs: Mapping[str, PathsOf],
    outputs: Mapping[str, PathsOf],
    appended: Mapping[str, PathsOf] | None = None,
) -> None:
    """Refuse outputs that would destroy something: call it before any work is done.

    ``inputs``, ``outputs`` (files written whole) and ``appended`` (files
    appended to, such as ``--log-file``) map an option name (``"--data"``) to
    the path(s) given, None for an option left out. Refused: an output that is
    the same file (same inode, or the same path once resolved) as an input or
    another output, and an output that exists and is not a regular file
    (:func:`refuse_special`).

    Raises
    ------
    InputError
        Naming the file and both options.
    OutputError
        Naming the file, its option and what it is.
    """
    written: list[tuple[str, Path]] = []
    groups = ((outputs, False), (appended or {}, True))
    for group, is_appended in groups:
        for out_option, out_paths in group.items():
            for out_path in _each(out_paths):
                refuse_special(out_path, out_option, is_appended)
                _refuse_same(out_option, out_path, inputs, written, is_appended)
                written.append((out_option, out_path))


def _refuse_same(
    out_option: str,
    out_path: Path,
    inputs: Mapping[str, PathsOf],
    written: list[tuple[str, Path]],
    appended: bool,
) -> None:
    harm = "written into" if appended else "replaced"
    for in_option, in_paths in inputs.items():
        if any(same_file(out_path, in_path) for in_path in _each(in_paths)):
            raise InputError(
                located(
                    out_path,
                    out_option,
                    f"is also the {in_option} file; it would be {harm} (write to another file)",
                )
            )
    for other_option, other in written:
        if same_file(out_path, other):
            raise InputError(located(out_path, out_option, f"is also the {other_option} file"))


def refuse_replacing(
    outputs: Mapping[str, PathsOf], force: bool, force_option: str = "--force"
) -> None:
    """Refuse to replace an existing file unless the user said ``--force``
    (``force_option``: how the caller says it, ``replace=True`` in the Python API).

    For the files a later step was made with (a plan, a pose) or that a user
    may have put there (a controller's tables in ``comp --out``); a link's target
    is what exists (a dangling link names a new file).

    Raises
    ------
    InputError
        Naming the first existing file and its option.
    """
    if force:
        return
    for option, paths in outputs.items():
        for path in _each(paths):
            if path.is_file():
                raise InputError(
                    located(
                        path,
                        option,
                        f"already exists and is not replaced; add {force_option} to replace"
                        " it, or give another file name",
                    )
                )


#: Bytes of the target's name kept in a temporary file's name: with the dot, the random
#: part and ``.tmp`` it stays within the 255 bytes a name may have.
TEMPORARY_NAME_BYTES = 200


def _temporary_prefix(path: Path) -> str:
    """``.NAME.`` of a temporary file next to ``path``, NAME cut to
    :data:`TEMPORARY_NAME_BYTES` (a name of 250 bytes is valid; its temporary one too)."""
    kept = os.fsencode(path.name)[:TEMPORARY_NAME_BYTES].decode("utf-8", "ignore")
    return f".{kept}."


def _write_temporary(path: Path, data: bytes) -> Path:
    """``data`` in a synced temporary file next to ``path`` (a link's target), mode
    ``0666 & ~umask``."""
    refuse_special(path, "cannot write")
    folder = next((p for p in path.parents if p.exists()), None)
    if folder is not None and not folder.is_dir():
        raise OutputError(located(path, "cannot write", f"{folder} is a file, not a folder"))
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(prefix=_temporary_prefix(path), suffix=".tmp", dir=path.parent)
    except OSError as error:
        raise OutputError(located(path, "cannot write", os_problem(error))) from error
    tmp = Path(name)
    try:
        with os.fdopen(fd, "wb") as handle:
            os.fchmod(handle.fileno(), _new_file_mode())
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
    except BaseException as error:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        if isinstance(error, OSError):
            raise OutputError(located(path, "cannot write", os_problem(error))) from error
        raise
    return tmp


def atomic_write_files(files: Mapping[Path, bytes]) -> None:
    """Write several files so that either all are replaced or none is.

    Every file is first written to a synced temporary file next to it (mode
    ``0666 & ~umask``, as a plain ``open`` would give: a controller running as
    another user can read it); only when all are written are they renamed
    over their targets. Folders are created if missing. A symbolic link is
    followed: its target is written and the link left as it is (a dangling
    link's target is created); a link that loops is refused.

    Raises
    ------
    OutputError
        A target is a folder, or a folder is read-only, the disk full...;
        every old file is then left as it was and no temporary file remains.
    """
    written: dict[Path, Path] = {}
    targets = {
        link_target(Path(path)) if Path(path).is_symlink() else Path(path): data
        for path, data in files.items()
    }
    try:
        for path, data in targets.items():
            written[path] = _write_temporary(path, data)
        for path, tmp in list(written.items()):
            try:
                os.replace(tmp, path)
            except OSError as error:
                raise OutputError(located(path, "cannot write", os_problem(error))) from error
            del written[path]
    finally:
        for tmp in written.values():
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)
    for folder in {path.parent for path in targets}:
        sync_folder(folder)


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write one file so that a reader sees the old file or the whole new one, never half.

    See :func:`atomic_write_files` (temporary file, fsync, rename; umask honoured).
    """
    atomic_write_files({Path(path): data})


def atomic_write_text(path: str | Path, text: str) -> None:
    """:func:`atomic_write_bytes` of UTF-8 text."""
    atomic_write_bytes(path, text.encode("utf-8"))


def write_json(path: str | Path, data: dict[str, Any]) -> None:
    """Write a JSON document atomically, indented for people.

    Raises
    ------
    OutputError
        A value is NaN or infinite: strict JSON has no such number, and
        xmalign's readers would refuse the file.
    """
    try:
        text = json.dumps(data, indent=2, allow_nan=False) + "\n"
    except ValueError as error:
        raise OutputError(
            located(path, "cannot write", "a value is not a finite number")
        ) from error
    atomic_write_text(path, text)
