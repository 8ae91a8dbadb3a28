"""Decode a Pioneer capture's received bytes directly with the codec (no client): the reference the client
and the raw replay are compared with."""

from __future__ import annotations

from drivers.capture import Capture
from drivers.pioneer.odometry import OdometryTracker, model_for
from drivers.pioneer.packets import SIP_IDS, PacketParser
from drivers.pioneer.sip import decode_sip, decode_sync2


def decode_rx(capture: Capture):
    """Identity, number of SIPs after the robot's SYNC2 reply and the final odometry, from the rx bytes alone."""
    info, tracker, n, odom = None, None, 0, None
    for pkt in PacketParser().feed(capture.rx_bytes()):
        if pkt.pid == 2 and pkt.payload:
            info = decode_sync2(pkt.payload)
            tracker = OdometryTracker(model_for(info.subclass))
        elif pkt.pid in SIP_IDS and tracker is not None:
            odom = tracker.update(decode_sip(pkt.pid, pkt.payload), 0.0)
            n += 1
    return info, n, odom
