"""Root of the driver exception tree (each device adds its own subclasses)."""


class DriverError(Exception):
    """Base class of every error raised by the drivers."""


class InvalidURL(DriverError, ValueError):
    """A device URL that cannot name a link (unknown scheme, missing host or port, bad baud rate)."""


class TransportError(DriverError):
    """The byte link failed: cannot open, closed by the peer, or I/O error."""


class TransportClosed(TransportError):
    """The peer closed the link (EOF) or the transport was closed locally."""


class DeviceTimeout(DriverError):
    """A device did not answer within the allowed time."""


class ProtocolError(DriverError):
    """Bytes that do not follow the protocol (reported by the codecs, never fatal to a stream)."""
