"""One exception root for everything scanpipe reports to a user.

The CLI turns a :class:`ScanpipeError` into a one-line message and a non-zero exit code.
Any other exception is a bug and keeps its traceback. Third-party exceptions are wrapped at
the boundary of the layer that calls them: ``raise StageError(...) from err``.
"""

from __future__ import annotations


class ScanpipeError(Exception):
    """Root of every error meant for the user. ``exit_code`` is what the CLI exits with."""

    exit_code: int = 1


class UsageError(ScanpipeError):
    """A command-line argument is invalid (exit code 2, like argument parsing errors)."""

    exit_code = 2


class ParameterError(UsageError):
    """One or more parameters failed validation; the message lists every problem."""

    def __init__(self, problems: list[str], source: str = "parameters") -> None:
        self.problems = list(problems)
        self.source = source
        if len(self.problems) == 1:
            message = f"{source}: {self.problems[0]}"
        else:
            lines = "\n".join(f"  {source}: {p}" for p in self.problems)
            message = f"{source}: {len(self.problems)} problems\n{lines}"
        super().__init__(message)


class RigError(ParameterError):
    """The rig description (TOML) is missing, unreadable or invalid."""


class PlanError(UsageError):
    """A scan plan cannot be made (angle out of range, limit exceeded)."""


class ProtocolError(ScanpipeError):
    """Bytes from a device could not be understood."""


class RecordingError(ScanpipeError):
    """A recording (MCAP) is missing, unreadable or not a scanpipe recording."""


class ArtifactError(ScanpipeError):
    """An artifact (Parquet) is missing, of the wrong kind, or has the wrong schema."""


class StageError(ScanpipeError):
    """A processing stage failed on its input."""


class DeviceError(ScanpipeError):
    """A device (scanner, motor controller, camera) misbehaved or could not be reached."""


class SimulationError(ScanpipeError):
    """The virtual rig could not be set up (scene, sensor model, emulator)."""


class ExportError(ScanpipeError):
    """A result could not be exported to the requested format or path."""


class MissingDependencyError(ScanpipeError):
    """An optional package a feature needs is not installed; the message says how to install."""


class LiveError(UsageError):
    """The live view could not be served (the port is taken or not allowed)."""
