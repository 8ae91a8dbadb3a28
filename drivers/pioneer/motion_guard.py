"""Scripted motions stop at a reconnect instead of resuming by themselves.

The client re-opens a lost link on its own and comes back at rest (setpoint zero). A script that keeps
sending setpoints from its odometry loop would set the robot moving again with nobody having decided so;
:class:`ReconnectGuard` makes it stop and report, unless the caller asked to continue.
"""

from __future__ import annotations

from drivers.pioneer.errors import PioneerError


class MotionInterrupted(PioneerError):
    """The link to the robot was lost and re-opened during a scripted motion; the motion was abandoned."""


class ReconnectGuard:
    """Watches a client's reconnect counter across one scripted motion.

    ``check()`` raises :class:`MotionInterrupted` once the client has reconnected since the guard was made,
    unless ``resume`` is true (then it only reports the reconnects it has seen, through ``seen``).
    """

    def __init__(self, base, resume: bool = False, what: str = "motion") -> None:
        self.base = base
        self.resume = resume
        self.what = what
        self.start = base.stats.reconnects
        self.seen = 0

    def check(self) -> None:
        n = self.base.stats.reconnects - self.start
        if n <= self.seen:
            return
        self.seen = n
        if not self.resume:
            raise MotionInterrupted(
                f"{self.what} abandoned: the link to the robot was lost and re-opened ({n} reconnect"
                f"{'s' if n > 1 else ''}); the robot is stopped. Check the cable or network and run it again, "
                "or pass --continue-after-reconnect to carry on by itself")
