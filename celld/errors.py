"""The one error tree of celld.

Every error celld raises derives from :class:`CelldError`. Third-party errors
are translated where they enter (``raise CalibrationError(...) from exc``), so a
caller never has to know which library failed::

    CelldError
    ├── ConfigError            a config file or value is refused (file, key, reason)
    ├── InputError             data from outside is malformed (shape, units, NaN, ...)
    │   └── JobError           a job message is refused (field, reason)
    ├── CalibrationError       a calibration cannot be solved or is degenerate
    │   └── DetectionError     the flange was not found in a cloud
    ├── SeamError              a seam cannot be found or fails its quality gate
    │   ├── WorkpieceError     the part model or its seam file is unusable
    │   ├── ScanError          the scan is empty, partial, or in the wrong units
    │   ├── RegistrationError  the model does not fit the scan on any seed
    │   └── GrooveError        the joint walls contradict the model or are not measurable
    ├── TactileError           the SRM camera or tag detection failed
    ├── DeviceError            a device (scanner, camera) failed or is absent
    │   └── DriverUnavailable  the SDK or hardware of a real driver is absent
    ├── RobotError             the robot link failed or the robot refused
    │   ├── LinkLost           the RTDE link dropped or went stale
    │   └── SafetyStop         a protective stop, e-stop or limit breach
    ├── MotionError            the motion process failed or refused a command
    │   └── PathRefused        a move would hit the cell or cannot be reached (checked before it starts)
    ├── BusError               the zenoh bus failed or refused a request
    ├── JournalError           the job journal refused a change or is damaged
    ├── StateFormatError       the state directory is of a format this release does not read
    ├── RecordingError         a job recording cannot be written
    └── StorageError           a write to the state directory failed (disk full, I/O error, read-only)
        ├── JournalWriteError  ... the journal's (also a JournalError)
        └── RecordingWriteError ... a recording's file (also a RecordingError)

In the 500 Hz loop nothing raises: controllers return status values instead.
"""

from __future__ import annotations


class CelldError(Exception):
    """Base of every error celld raises."""


class ConfigError(CelldError):
    """A configuration file or value was refused.

    Parameters
    ----------
    source : str
        The file (or other source) the value came from.
    key : str
        The dotted key path of the offending value, ``""`` for the whole file.
    reason : str
        What was expected and what came.
    """

    def __init__(self, source: str, key: str, reason: str) -> None:
        self.source = source
        self.key = key
        self.reason = reason
        where = f"{source}: {key}" if key else source
        super().__init__(f"{where}: {reason}")


class InputError(CelldError):
    """Data from outside (a cloud, an image, a file, a message) is malformed."""


class JobError(InputError):
    """A job message was refused; ``field`` names the offending field."""

    def __init__(self, field: str, reason: str) -> None:
        self.field = field
        self.reason = reason
        super().__init__(f"{field}: {reason}" if field else reason)


class CalibrationError(CelldError):
    """A calibration could not be solved, or its input is degenerate."""


class DetectionError(CalibrationError):
    """The flange was not found in a cloud; ``stage`` says where it failed."""

    def __init__(self, stage: str, reason: str) -> None:
        self.stage = stage
        self.reason = reason
        super().__init__(f"flange detection failed at {stage}: {reason}")


class SeamError(CelldError):
    """A seam could not be found or failed its quality gate.

    ``reason`` says what was expected and what came; ``figures`` holds the
    quality figures measured before the refusal (SI units), for reports.
    """

    def __init__(self, reason: str, figures: dict[str, float] | None = None) -> None:
        self.reason = reason
        self.figures = dict(figures or {})
        super().__init__(reason)


class WorkpieceError(SeamError):
    """The part model (mesh, seam polyline, seam file) is unusable."""


class ScanError(SeamError):
    """The scan is empty, covers too little of the seam, or has the wrong units."""


class RegistrationError(SeamError):
    """The part model does not fit the scan: gate failed on every seed."""


class GrooveError(SeamError):
    """The joint walls in the scan contradict the model, or cannot be measured."""


class TactileError(CelldError):
    """The SRM camera or the tag detection failed."""


class DeviceError(CelldError):
    """A device (scanner, camera) failed or is absent."""


class DriverUnavailable(DeviceError):
    """The SDK or the hardware that a real driver needs is absent."""


class RobotError(CelldError):
    """The robot link failed or the robot refused a command."""


class LinkLost(RobotError):
    """The RTDE link dropped or its data went stale."""


class StaleState(LinkLost):
    """The motion loop stopped a command on robot state older than its limit (the link itself stayed up)."""


class SafetyStop(RobotError):
    """A protective stop, an e-stop or a limit breach stopped the robot."""


class MotionError(CelldError):
    """The motion process failed, or refused a command."""


class PathRefused(MotionError):
    """A move, a calibration pose or a weld path was refused before the robot moved: it would hit
    the cell (which part, which object), is out of reach, crosses a singularity or leaves the IK branch."""


class BusError(CelldError):
    """The zenoh bus failed or refused a request."""


class JournalError(CelldError):
    """The job journal refused a change (an illegal transition, an unknown job) or is damaged."""


class JournalDamagedError(JournalError):
    """The job journal's database is damaged (SQLite ``SQLITE_CORRUPT``, a failed integrity check).

    Not a write that can be made again later: the journal stays refused until
    an operator sets it aside (``celld journal set-aside``).
    """


class StateFormatError(CelldError):
    """The state directory is of a newer format than this release reads, has no migration to it, or is not one."""


class DamagedStateError(CelldError):
    """A file the cell keeps (the current calibration, the tool's, the finger's rest) cannot be trusted:
    unreadable, truncated, edited (its checksum fails), of an unknown format.

    Parameters
    ----------
    what : str
        Which state, as the operator names it: ``calibration``, ``tool calibration``, ``finger rest``.
    path : str
        The file.
    why : str
        What is wrong with it.
    """

    def __init__(self, what: str, path: str, why: str) -> None:
        self.what = what
        self.path = path
        self.why = why
        super().__init__(f"the stored {what} is damaged: {why} ({path})")


class RecordingError(CelldError):
    """A job recording (the rerun ``.rrd`` file) cannot be created or written."""


class StorageError(CelldError):
    """A write to the cell's state directory failed: the disk is full, an I/O error, a read-only file system.

    Parameters
    ----------
    what : str
        Which store: ``journal``, ``result``, ``job files`` (datasets, paths),
        ``recording``, ``calibration``, ``probe``.
    path : str
        The file (or database) that could not be written.
    reason : str
        The operating system's or SQLite's words (``No space left on device``).
    errno : int or None
        The errno, when the failure came with one.
    """

    def __init__(self, what: str, path: str, reason: str, errno: int | None = None) -> None:
        self.what = what
        self.path = path
        self.reason = reason
        self.errno = errno
        super().__init__(f"storage: {what} {path}: {reason}" if path else f"storage: {what}: {reason}")


class JournalWriteError(JournalError, StorageError):
    """The journal could not commit a change (SQLite ``SQLITE_FULL``, ``SQLITE_IOERR``, ...)."""


class RecordingWriteError(RecordingError, StorageError):
    """A recording's ``.rrd`` file could not be created or written; the recording is incomplete."""
