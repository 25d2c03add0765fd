"""The one exception hierarchy of xmalign.

Every error that a user can cause or a device can raise derives from
:class:`XmalignError`; the CLI turns it into one line on stderr and exit code 2.
Subclasses also inherit the matching built-in so that generic handlers work.
Device faults (the device answered and said no) are kept apart from transport
failures (the device did not answer).
"""

from __future__ import annotations


class XmalignError(Exception):
    """Base class of every xmalign error."""


class InputError(XmalignError, ValueError):
    """Bad user input: a file, key, option or value that cannot be used."""


class MachineKeyError(InputError):
    """A key of the machine file that cannot serve what was asked of it.

    Raised where the file's name is not known (a compensation writer); the command
    that read the file names it: ``FILE: key: problem``.
    """

    def __init__(self, key: str, problem: str) -> None:
        super().__init__(f"{key}: {problem}")
        self.key = key
        self.problem = problem

    def in_file(self, source: str) -> InputError:
        """The same error naming the machine file it is about."""
        return InputError(f"{source}: {self.key}: {self.problem}")


class FormatError(InputError):
    """A file whose format, version or syntax xmalign does not know."""


class OutputError(XmalignError, OSError):
    """A file could not be written: no permission, a full disk, a folder in the way."""


class GeometryError(XmalignError, ValueError):
    """A setup whose geometry cannot give a result (degenerate, out of reach)."""


class OutOfRangeError(XmalignError, ValueError):
    """A target outside a travel, an axis range or an instrument range."""


class DeviceError(XmalignError):
    """A device answered and reported a fault (drive fault, beam lost, refused move)."""


class BeamLostError(DeviceError):
    """The interferometer lost its beam (a channel left its range)."""


class DriveFaultError(DeviceError):
    """A positioning-unit axis or CNC reported a fault."""


class TransportError(XmalignError, ConnectionError):
    """A device did not answer: connection refused, dropped or corrupted."""


class DeviceTimeoutError(TransportError, TimeoutError):
    """A device did not answer or did not finish in time."""


class HeartbeatError(DriveFaultError):
    """A unit's heartbeat watchdog stopped and locked its axes (fault 4): the host went stale.

    A device fault, not a transport failure: the unit answers and says its axes
    are stopped and locked; reconnecting alone does not undo it, a fault reset
    after the heartbeat is running again does (docs/registers.md, "Watchdog").
    Every implementation of a positioning unit (Modbus, CANopen, simulated)
    raises this class for it.
    """
