"""Errors that the CLI turns into one clear line and a non-zero exit."""

from __future__ import annotations


class CfraceError(Exception):
    """A user-facing error: bad input, a refused operation. Printed as one line, exit code 2."""

    exit_code = 2


class ConfigError(CfraceError):
    """A malformed track, calibration or config file. The message names file, key and problem."""


class PolicyError(CfraceError):
    """A corrupt, wrong-sized or mismatched ONNX policy."""


class LinkError(CfraceError):
    """A drone link that could not be opened or was lost."""


class MocapError(CfraceError):
    """A motion-capture source that could not be opened or named an unknown body."""


class LogError(CfraceError):
    """A flight log that cannot be read (truncated, corrupt, wrong schema)."""


class FlightError(CfraceError):
    """A flight procedure that could not be completed (e.g. the drones did not settle at their start)."""


class CfraceWarning(RuntimeWarning):
    """Something works, but not as asked or not as fast (e.g. the simulator's slower fallback);
    the `cfrace` command prints it as one line ``warning: ...``."""
