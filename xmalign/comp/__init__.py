"""Compensation tables for CNC controllers, one module per controller.

Each module has ``NAME``, ``MODEL`` (a :class:`~xmalign.comp.fit.CompModel`: what
its tables can apply), ``render(fit, machine) -> {file name: text}`` and
``loading(fit, machine) -> Loading`` (who carries the reversal, the one check on
the machine, what the maker's manual left open). The
tables are fitted once, here, by :func:`~xmalign.comp.fit.fit_compensation`
over the machine's whole travel at its tool point; a writer only formats them.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from types import ModuleType

from xmalign.comp import fanuc, heidenhain, isg, linuxcnc, sinumerik
from xmalign.comp.common import Loading, table_sources
from xmalign.comp.fit import CompensationFit, fit_compensation
from xmalign.errors import InputError
from xmalign.formats.error_tables import ErrorTableSet
from xmalign.machine import SERIES, Machine
from xmalign.rigid_body import Chain, ErrorModel, RemainingErrors

WRITERS: dict[str, ModuleType] = {
    module.NAME: module for module in (sinumerik, fanuc, heidenhain, linuxcnc, isg)
}


def writer(controller: str) -> ModuleType:
    """The writer module of a controller; InputError listing the known ones."""
    try:
        return WRITERS[controller]
    except KeyError:
        raise InputError(
            f"unknown controller '{controller}' (one of {', '.join(WRITERS)})"
        ) from None


def for_controller(machine: Machine, controller: str) -> Machine:
    """``machine`` as seen by ``controller``'s writer: another family than the machine
    file's ``controller`` (``xmalign comp --controller``) gets that family's default series
    unless ``cnc.series`` is one of its own (docs/controllers.md)."""
    if controller == machine.controller or controller not in SERIES:
        return machine
    series = machine.cnc.series if machine.cnc.series in SERIES[controller] else None
    cnc = machine.cnc.model_copy(update={"series": series})
    return machine.model_copy(update={"controller": controller, "cnc": cnc})


def fit_for(machine: Machine, tables: ErrorTableSet, controller: str) -> CompensationFit:
    """The controller's tables fitted over the machine's travel at its tool point (with
    the error-table file they came from, for the files' history)."""
    fit = fit_compensation(
        writer(controller).MODEL,
        tables,
        Chain.parse(machine.chain),
        (machine.travel_min_mm, machine.travel_max_mm),
        machine.cnc.tool_offset,
        machine.cnc.reference,
    )
    return replace(fit, sources=table_sources(tables))


@dataclass(frozen=True)
class Compensation:
    """What ``xmalign comp`` produced: the fit (residuals), the files and how to load them."""

    controller: str
    fit: CompensationFit
    files: dict[str, str]
    loading: Loading
    #: LinuxCNC with an INI (``comp --ini``): the merged copy written and each joint's axis
    merged_ini: Path | None = None
    joints: tuple[str, ...] = ()


def compensate(machine: Machine, tables: ErrorTableSet, controller: str) -> Compensation:
    """Fit the controller's model and format its files (the family's default series when
    ``controller`` is not the machine file's, :func:`for_controller`)."""
    module = writer(controller)
    machine = for_controller(machine, controller)
    fit = fit_for(machine, tables, controller)
    return Compensation(controller, fit, module.render(fit, machine), module.loading(fit, machine))


def remaining_errors(tables: ErrorTableSet, controller: str, machine: Machine) -> ErrorModel:
    """The error model left after the controller's fitted tables (direction-free)."""
    return RemainingErrors(tables.model(""), fit_for(machine, tables, controller).mean)


__all__ = [
    "WRITERS",
    "Compensation",
    "Loading",
    "compensate",
    "fit_for",
    "for_controller",
    "remaining_errors",
    "writer",
]
