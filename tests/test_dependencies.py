"""Every runtime dependency is declared (issue 32): a plain ``pip install -e .`` runs.

``sim serve --canopen`` (and ``run``/``align --live`` on ``udp_local`` units) ended in
"msgpack not installed" after a plain install: python-can's ``udp_multicast``, under
the simulated bus, imports msgpack only when a bus is opened, which no look at our own
imports would see. So the packages run here with every installed module that the
declared dependencies (pyproject.toml ``[project] dependencies``, followed through
their own requirements) do not provide made unimportable, as in a fresh venv.

A real fresh venv takes over a minute to install (casadi, scipy, matplotlib); it was run
by hand once (issue 32's report): ``python -m venv V && V/bin/pip install -e . &&
V/bin/xmalign sim serve --canopen 239.74.1.1`` failed without msgpack, serves with it.
"""

from __future__ import annotations

import ast
import json
import os
import signal
import subprocess
import sys
import tomllib
import uuid
from importlib import metadata
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parents[1]
OURS = ("xmalign", "firmware_iface", "trajectories", "sim")
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
#: Extras a user chooses (not the test tools).
USER_EXTRAS = [name for name in PROJECT["optional-dependencies"] if name != "test"]


def _closure(requirements: list[str]) -> set[str]:
    """The distributions ``requirements`` bring, their requirements followed (installed ones)."""
    found: set[str] = set()
    pending = [(Requirement(text), "") for text in requirements]
    while pending:
        requirement, extra = pending.pop()
        if requirement.marker is not None and not requirement.marker.evaluate({"extra": extra}):
            continue
        name = canonicalize_name(requirement.name)
        if name in found:
            continue
        found.add(name)
        wanted = list(requirement.extras) or [""]
        try:
            texts = metadata.requires(requirement.name) or []
        except metadata.PackageNotFoundError:  # an extra not installed here (o6)
            continue
        pending += [(Requirement(text), want) for text in texts for want in wanted]
    return found


def _modules_of(distributions: set[str]) -> set[str]:
    """Top-level modules installed by ``distributions``."""
    return {
        module
        for module, owners in metadata.packages_distributions().items()
        if any(canonicalize_name(owner) in distributions for owner in owners)
    }


REQUIRED = _modules_of(_closure(PROJECT["dependencies"])) | set(OURS)
OPTIONAL = _modules_of(
    _closure([text for extra in USER_EXTRAS for text in PROJECT["optional-dependencies"][extra]])
)
#: Installed here, yet not brought by a plain install.
NOT_DECLARED = sorted(set(metadata.packages_distributions()) - REQUIRED)


def _imports(path: Path) -> list[tuple[str, int, bool]]:
    """(module, line, at the module's top level) of each absolute import."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    top = {id(node) for node in tree.body}
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module]
        else:
            continue
        found += [(name, node.lineno, id(node) in top) for name in names]
    return found


#: Our modules that need an extra throughout; each is imported only inside the function
#: of the command that uses it.
EXTRA_MODULES = {"firmware_iface.sinumerik_opcua": "opcua"}


def _sources() -> list[tuple[str, Path]]:
    return [
        (".".join(path.relative_to(ROOT).with_suffix("").parts), path)
        for package in OURS
        for path in sorted((ROOT / package).rglob("*.py"))
    ]


def test_every_third_party_import_is_declared():
    """A module-level import needs a declared dependency; one inside a function (loaded
    by the command that uses it) may come from an extra (dask, pandas, asyncua)."""
    missing = []
    for name, path in _sources():
        for module, line, top in _imports(path):
            where = f"{path.relative_to(ROOT)}:{line}: {module}"
            if module in EXTRA_MODULES and top:
                missing.append(where + f" (needs the '{EXTRA_MODULES[module]}' extra)")
            first = module.partition(".")[0]
            if first in sys.stdlib_module_names or first in REQUIRED:
                continue
            if (top and name not in EXTRA_MODULES) or first not in OPTIONAL:
                missing.append(where)
    assert not missing, missing
    assert "msgpack" in REQUIRED  # python-can's udp_multicast opens no bus without it


#: Run before xmalign's own code: every installed module a plain install would not have
#: becomes a ModuleNotFoundError, as in a fresh venv.
_PLAIN_INSTALL = """
import importlib.abc, json, runpy, sys
blocked = set(json.loads(sys.argv.pop(1)))
class PlainInstall(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if path is None and name in blocked:
            raise ModuleNotFoundError(f"No module named {name!r} (not declared)", name=name)
        return None
sys.meta_path.insert(0, PlainInstall())
sys.argv[0] = "xmalign"
runpy.run_module("xmalign", run_name="__main__")
"""


def test_sim_serve_canopen_runs_with_the_declared_dependencies_only():
    group = "239.74.{}.{}".format(*uuid.uuid4().bytes[:2])
    process = subprocess.Popen(
        [sys.executable, "-c", _PLAIN_INSTALL, json.dumps(NOT_DECLARED)]
        + ["sim", "serve", "--canopen", group],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "COLUMNS": "200", "PYTHONPATH": str(ROOT)},
        cwd=ROOT,
    )
    try:
        said = []
        while not any("serving" in line for line in said):
            line = process.stdout.readline()  # type: ignore[union-attr]
            assert line, process.stderr.read()  # type: ignore[union-attr]
            said.append(line)
    finally:
        process.send_signal(signal.SIGINT)
        _, errors = process.communicate(timeout=30)
    assert process.returncode == 0, errors
    assert "canopen nodes" in "".join(said)
