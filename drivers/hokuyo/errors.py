"""Hokuyo SCIP errors: status codes from the sensor, and corrupt bytes reported by the codec.

Two families:
- :class:`ScipStatusError` (and one subclass per well-known code): the sensor answered a command with a
  non-success status. Carries the raw 2-char ``code`` and the ``command`` it answered.
- :class:`ScipProtocolError` (a ``drivers.errors.ProtocolError``): bytes that do not follow SCIP. The
  parser never raises these; it *reports* them as values next to the replies it decodes and resynchronises.
"""

from __future__ import annotations

from drivers.errors import DeviceTimeout, DriverError, ProtocolError


class HokuyoError(DriverError):
    """Base class of the Hokuyo driver's errors."""


class ScipStatusError(HokuyoError):
    """The sensor answered ``command`` with status ``code`` (raw 2 chars, e.g. ``"0L"``)."""

    hint = "see the SCIP 2.0 status table"

    def __init__(self, code: str, command: str, message: str | None = None) -> None:
        self.code = code
        self.command = command
        super().__init__(message or f"sensor answered {command!r} with status {code!r}: {self.hint}")


class UndefinedCommand(ScipStatusError):
    """0E: the command is not defined on this sensor."""

    hint = "command not defined on this model (0E)"


class UnsupportedCommand(ScipStatusError):
    """0F: the command exists in SCIP but this sensor does not support it."""

    hint = "command not supported by this model (0F)"


class StringTooLong(ScipStatusError):
    """0G: the ``;string`` part of the command was longer than 16 characters."""

    hint = "command string longer than 16 characters (0G)"


class CommandRejected(ScipStatusError):
    """0A-0I (other than 0E/0F/0G) or 01-09: malformed command or parameters."""

    hint = "malformed command or parameter out of range"


class AbnormalState(ScipStatusError):
    """0L: the sensor is in an abnormal state (hardware fault; power-cycle or RB)."""

    hint = "sensor in abnormal state (0L): check power and the motor, then reboot the sensor"


class Unstable(ScipStatusError):
    """0M: the sensor is unstable (motor not at speed yet, e.g. just after boot)."""

    hint = "sensor unstable (0M): motor not at speed yet, retry in a few seconds"


class Denied(ScipStatusError):
    """10: the command is not allowed in the current state (e.g. GD with the laser off)."""

    hint = "command denied in the current sensor state (10)"


_BY_CODE: dict[str, type[ScipStatusError]] = {
    "0E": UndefinedCommand,
    "0F": UnsupportedCommand,
    "0G": StringTooLong,
    "0L": AbnormalState,
    "0M": Unstable,
    "10": Denied,
}


def status_error(code: str, command: str) -> ScipStatusError:
    """The most specific :class:`ScipStatusError` for a raw status ``code`` answering ``command``."""
    cls = _BY_CODE.get(code)
    if cls is None:
        cls = CommandRejected if (code[:1] == "0" and code != "00") else ScipStatusError
    return cls(code, command)


class ScipProtocolError(ProtocolError, HokuyoError):
    """Bytes that do not follow SCIP; ``command`` is the echo's command when known, ``data`` a prefix of
    the offending bytes (at most 64)."""

    def __init__(self, message: str, *, command: str = "", data: bytes = b"") -> None:
        self.command = command
        self.data = bytes(data[:64])
        super().__init__(message)


class ChecksumError(ScipProtocolError):
    """A status or data line failed its checksum."""


class TruncatedMessage(ScipProtocolError):
    """A message ended early: missing lines, a new message began inside it, or too few values."""


class UnexpectedEcho(ScipProtocolError):
    """An echo line that is not a SCIP command (or a reply nobody asked for)."""


class GarbageData(ScipProtocolError):
    """Bytes between messages that belong to no message (line noise); ``nbytes`` counts them."""

    def __init__(self, message: str, *, data: bytes = b"", nbytes: int = 0) -> None:
        super().__init__(message, data=data)
        self.nbytes = nbytes


class BadValue(ScipProtocolError):
    """Payload characters outside the 6-bit alphabet, or data whose length does not fit the command."""


class SensorSilent(DeviceTimeout, HokuyoError):
    """No scan arrived for longer than the watchdog allows (cable pulled, sensor hung or rebooting)."""


class StopNotConfirmed(DeviceTimeout, HokuyoError):
    """QT was sent several times but the sensor kept streaming or never answered."""
