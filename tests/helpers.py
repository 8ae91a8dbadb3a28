"""Polling helpers shared by the tests: wait for a condition with a generous bound and a message that names
what was awaited (a bound against hanging, never a timing assertion)."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

import pytest


async def eventually(pred: Callable[[], bool], timeout: float = 10.0, what: str = "condition",
                     interval: float = 0.01) -> None:
    """Poll ``pred`` in the event loop until it holds; fail naming ``what`` if it does not within ``timeout`` s."""
    end = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > end:
            pytest.fail(f"{what} did not happen within {timeout} s")
        await asyncio.sleep(interval)


def wait_until(pred: Callable[[], bool], timeout: float = 10.0, what: str = "condition",
               interval: float = 0.01) -> None:
    """``eventually`` for code outside an event loop (threads, subprocesses)."""
    end = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > end:
            pytest.fail(f"{what} did not happen within {timeout} s")
        time.sleep(interval)
