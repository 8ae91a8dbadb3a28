"""The one way the device clients connect: ``Client.connect(url, settings)`` returns a :class:`Connecting`.

    async with HokuyoClient.connect(url, HokuyoSettings(cluster=2)) as laser:   # closed on exit
        ...
    base = await PioneerClient.connect(url, PioneerSettings(max_v=0.3))        # close() yourself
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Generator
from typing import Any, Generic, Protocol, TypeVar


class _Client(Protocol):
    async def __aexit__(self, *exc: object) -> None: ...


C = TypeVar("C", bound=_Client)


class Connecting(Generic[C]):
    """A pending connection: ``await`` it for the client, or ``async with`` it to have the client closed
    on exit (also on errors and cancellation)."""

    def __init__(self, factory: Callable[[], Awaitable[C]]) -> None:
        self._factory = factory
        self._client: C | None = None

    def __await__(self) -> Generator[Any, None, C]:
        return self._factory().__await__()  # type: ignore[attr-defined]

    async def __aenter__(self) -> C:
        self._client = await self._factory()
        return self._client

    async def __aexit__(self, *exc: object) -> None:
        if self._client is not None:
            client, self._client = self._client, None
            await client.__aexit__(*exc)  # the client's own exit: close, reporting close errors its way
