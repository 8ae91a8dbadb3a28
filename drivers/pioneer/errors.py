"""Errors of the Pioneer driver, rooted in :mod:`drivers.errors`.

Codec problems (:class:`PacketError` and subclasses) are reported by the sans-IO parser as counted events
and never stop a stream; the client raises the other classes. Bad arguments stay ``ValueError``.
"""

from __future__ import annotations

from drivers.errors import DeviceTimeout, DriverError, ProtocolError, TransportError


class PioneerError(DriverError):
    """Base class of every Pioneer driver error."""


class PacketError(ProtocolError, PioneerError):
    """Bytes that do not form a valid ARCOS packet (the parser drops them and re-synchronises)."""


class ChecksumError(PacketError):
    """A framed packet whose checksum does not match its contents."""


class FramingError(PacketError):
    """A header with an impossible length byte, or a packet cut short by an inter-byte timeout."""


class DecodeError(PacketError):
    """A packet with a valid checksum whose payload does not fit its packet type (too short, bad strings)."""


class HandshakeError(PioneerError):
    """The SYNC0/SYNC1/SYNC2 handshake or OPEN failed after the allowed retries."""


class HandshakeTimeout(HandshakeError, DeviceTimeout):
    """The robot did not answer the handshake at all."""


class UnsupportedRobotError(HandshakeError):
    """The robot reported a class/subclass the driver has no conversion factors for."""


class LinkLostError(PioneerError, TransportError):
    """The link to the robot is down (the client may be reconnecting); the command was not sent."""


class ClientClosedError(PioneerError):
    """The client was closed; no more commands or odometry."""
