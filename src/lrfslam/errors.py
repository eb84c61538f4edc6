"""The one exception hierarchy of lrfslam.

Every error the package raises on purpose derives from :class:`LrfSlamError`, so a
service shell can tell "bad input, count it and go on" (:class:`InputError` and its
children) from a bug (anything else), which must crash the process so its
supervisor restarts it.
"""

from __future__ import annotations


class LrfSlamError(Exception):
    """Base of every error lrfslam raises on purpose."""


class ConfigError(LrfSlamError):
    """A configuration value is unknown, of the wrong type, or out of range."""


class MissingExtraError(ConfigError):
    """A command needs an optional dependency (an extra of the distribution) that is not installed."""


class InputError(LrfSlamError):
    """Bad input data: the message, file line or telegram is skipped and counted."""


class DecodeError(InputError):
    """A payload could not be decoded with the schema it claims.

    Parameters
    ----------
    schema : str
        Schema name the payload claimed (``""`` when none was given).
    reason : str
        What was wrong, for the log line.
    """

    def __init__(self, schema: str, reason: str) -> None:
        self.schema = schema
        self.reason = reason
        super().__init__(f"cannot decode {schema or '<no schema>'}: {reason}")


class SchemaVersionError(DecodeError):
    """A payload carries a schema name or version this build does not know."""


class TelegramError(InputError):
    """An LMS200 telegram failed framing, length or CRC checks."""


class DeviceError(LrfSlamError):
    """The serial device disappeared, timed out, or answered out of protocol."""


class RecordingError(LrfSlamError):
    """An MCAP recording cannot be read or written."""


class StartupError(LrfSlamError):
    """A process of ``lrfslam up`` exited, or never came up, while the pipeline was starting."""


class MapError(LrfSlamError):
    """A map cannot be saved (its folder is taken, the recording has no mapper output) or read."""


class MapFormatError(MapError):
    """A saved map (``lrfslam map save``) lacks a file, is damaged, or has a format version this build cannot read."""
