"""One base error for slamlens, with a subclass per concern.

The CLI turns any :class:`SlamlensError` into one clear line and exit code 1;
subscribers drop and count messages that raise :class:`MessageError`.
"""

from __future__ import annotations


class SlamlensError(Exception):
    """Base of every error slamlens raises on purpose."""


class MessageError(SlamlensError):
    """A message could not be decoded or failed validation.

    ``field`` names the offending field, ``expected`` says what was required and
    ``actual`` what arrived, so one log line is enough to find the sender's bug.
    """

    def __init__(self, message_type: str, field: str, expected: str, actual: str) -> None:
        self.message_type = message_type
        self.field = field
        self.expected = expected
        self.actual = actual
        super().__init__(f"{message_type}.{field}: expected {expected}, got {actual}")


class ConfigError(SlamlensError):
    """A configuration file or flag is invalid (the key is named in the message)."""


class CalibrationError(SlamlensError):
    """A camera calibration file is unreadable or incomplete (file and field named)."""


class BusError(SlamlensError):
    """The Zenoh session could not be opened or used."""


class SourceError(SlamlensError):
    """A data source (camera, dataset, serial port) failed or is malformed."""


class SecurityError(SlamlensError):
    """A certificate, key or identity is missing, malformed or not of this authority
    (the file and the reason are named in the message)."""
