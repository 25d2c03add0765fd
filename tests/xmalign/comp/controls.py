"""Each control family reading back the files ``xmalign comp`` wrote, as its manual says.

What a control takes out, per direction of travel, as error tables ``E<output><input>``
(mm, the errors the control removes: a correction is minus them), read from the files
alone with each family's documented rules (docs/controllers.md):

- Sinumerik: LEC ``$AA_ENC_COMP`` values are errors (K3: "a positive compensation value
  moves the axis negative"); CEC ``$AN_CEC`` values are corrections (xmalign's reading,
  not confirmed from the manual), each table acting in the directions ``$AN_CEC_DIRECTION``
  gives; ``(MAX - MIN) / STEP`` must equal the number of points minus one exactly;
  a reversal left to MD32450 ``$MA_BACKLASH`` (the 828D's) acts when the axis moves
  against its reference-return direction, positive when the encoder leads the machine
  part (the ``-`` approach stops above the ``+`` approach).
- Fanuc: incremental corrections per section, the table of the reference-return
  direction zero at the reference position, the other direction's table there at
  parameter 3627 (A-77810E, table (a)); values x magnification x detection unit.
- Heidenhain: the axis column (positive direction) and ``BACKLASH`` (negative direction)
  hold errors at ``AXISPOS``.
- LinuxCNC: ``nominal forward reverse`` actual positions (type 0).

Written independently of the writers (it parses text), so a sign or datum slip in a
writer shows as a difference between what the control takes out and the fit.
"""

from __future__ import annotations

import re
from decimal import Decimal

import numpy as np

from xmalign.machine import Machine

AXES = ("X", "Y", "Z")
Tables = dict[str, tuple[np.ndarray, np.ndarray]]


def _grid(start: Decimal, step: Decimal, end: Decimal, count: int) -> np.ndarray:
    assert (end - start) / step == count - 1, (start, step, end, count)
    return float(start) + float(step) * np.arange(count)


def _add(tables: Tables, name: str, positions: np.ndarray, values: np.ndarray) -> None:
    if name in tables:
        old_positions, old = tables[name]
        assert np.allclose(old_positions, positions), name
        values = old + values
    tables[name] = (positions, values)


def _names(machine: Machine) -> dict[str, str]:
    return {machine.cnc.axis_name(axis, f"AX{i + 1}"): axis for i, axis in enumerate(AXES)}


def sinumerik(files: dict[str, str], machine: Machine, direction: str) -> Tables:
    """Errors taken out moving in ``direction`` (``+`` or ``-``)."""
    names = _names(machine)
    tables: Tables = {}
    lec = re.findall(
        r"^\$AA_ENC_COMP(_STEP|_MIN|_MAX)?\[0,(?:(\d+),)?(\w+)\]=(\S+)$", files["AX_EEC.INI"], re.M
    )
    for name, axis in names.items():
        values = [Decimal(v) for kind, _, n, v in lec if not kind and n == name]
        meta = {kind: Decimal(v) for kind, _, n, v in lec if kind and n == name}
        positions = _grid(meta["_MIN"], meta["_STEP"], meta["_MAX"], len(values))
        _add(tables, f"E{axis}{axis}", positions, np.array(values, dtype=float))
    cec = files["NC_CEC.INI"]
    for value, name in re.findall(r"MD32450 \$MA_BACKLASH\[0\] = (\S+) on (\w+)$", cec, re.M):
        axis = names[name]
        if direction != (machine.reference_return(axis) or "+"):
            # a positive backlash: the - approach stops above the + approach (808D MD32450)
            play = float(value) if direction == "-" else -float(value)
            positions, values = tables[f"E{axis}{axis}"]
            tables[f"E{axis}{axis}"] = (positions, values + play)
    for t in sorted({int(i) for i in re.findall(r"^\$AN_CEC\[(\d+),", cec, re.M)}):

        def value(key: str, t: int = t) -> str:
            return re.search(
                rf"^\$AN_CEC_{key}\[{t}\]=\(?(\w[^)\s]*|-?[\d.]+)\)?$", cec, re.M
            ).group(1)

        acts = int(value("DIRECTION"))
        if acts not in (0, 1 if direction == "+" else -1):
            continue
        corrections = [Decimal(v) for v in re.findall(rf"^\$AN_CEC\[{t},\d+\]=(\S+)$", cec, re.M)]
        positions = _grid(
            Decimal(value("MIN")), Decimal(value("STEP")), Decimal(value("MAX")), len(corrections)
        )
        output, source = names[value("OUTPUT_AXIS")], names[value("INPUT_AXIS")]
        _add(tables, f"E{output}{source}", positions, -np.array(corrections, dtype=float))
    return tables


def fanuc(files: dict[str, str], machine: Machine, direction: str) -> Tables:
    """Own-axis errors taken out moving in ``direction`` (pitch compensation only)."""
    tape = files["PITCH.TXT"]
    parameters = {
        int(number): [int(v) for v in re.findall(r"A\d+P(-?\d+)", rest)]
        for number, rest in re.findall(r"^N0(36\d\d)(?:Q1)?(.*);$", tape, re.M)
    }
    data = {int(n): int(v) for n, v in re.findall(r"^N1(\d{4})P(-?\d+);$", tape, re.M)}
    unit_mm = machine.cnc.detection_unit_um * 1e-3
    tables: Tables = {}
    for i, axis in enumerate(AXES):
        reference_number = parameters[3620][i]
        first, last = parameters[3621][i], parameters[3622][i]
        magnification, interval = parameters[3623][i], parameters[3624][i]
        reference = float(machine.cnc.reference[i])
        returns = machine.reference_return(axis) or "+"
        if direction == "-" and 3626 in parameters and parameters[3626][i]:
            offset = parameters[3626][i] - first
        else:
            offset = 0
        anchored_here = 3626 not in parameters or not parameters[3626][i] or direction == returns
        at_reference = 0 if anchored_here else parameters[3627][i]
        numbers = np.arange(first - 1, last + 1)
        absolute = [at_reference]
        for number in range(reference_number + 1, last + 1):
            absolute.append(absolute[-1] + data[number + offset])
        below = [at_reference]
        for number in range(reference_number, first - 1, -1):
            below.insert(0, below[0] - data[number + offset])
        correction = np.array(below[:-1] + absolute, dtype=float) * magnification * unit_mm
        positions = reference + (numbers - reference_number) * interval * unit_mm
        tables[f"E{axis}{axis}"] = (positions, -correction)
    return tables


def heidenhain(files: dict[str, str], machine: Machine, direction: str) -> Tables:
    """Errors taken out moving in ``direction``."""
    tables: Tables = {}
    for source in AXES:
        lines = files[f"{source}.COM"].splitlines()
        header = lines[1].split()
        rows = np.array([[float(v) for v in line.split()] for line in lines[2:-1]])
        positions = rows[:, header.index("AXISPOS")]
        for output in AXES:
            column = output
            if output == source and direction == "-" and "BACKLASH" in header:
                column = "BACKLASH"
            values = rows[:, header.index(column)] if column in header else 0 * positions
            tables[f"E{output}{source}"] = (positions, values)
    return tables


def linuxcnc(files: dict[str, str], machine: Machine, direction: str) -> Tables:
    """Own-axis errors taken out moving in ``direction`` (actual minus nominal)."""
    tables: Tables = {}
    for axis in AXES:
        rows = np.array(
            [
                [float(v) for v in line.split()]
                for line in files[f"{axis.lower()}.comp"].splitlines()
            ]
        )
        actual = rows[:, 1] if direction == "+" else rows[:, 2]
        tables[f"E{axis}{axis}"] = (rows[:, 0], actual - rows[:, 0])
    return tables


READERS = {"sinumerik": sinumerik, "fanuc": fanuc, "heidenhain": heidenhain, "linuxcnc": linuxcnc}


def taken_out(controller: str, files: dict[str, str], machine: Machine, direction: str) -> Tables:
    """What ``controller`` takes out moving in ``direction``, read from its files."""
    return READERS[controller](files, machine, direction)
