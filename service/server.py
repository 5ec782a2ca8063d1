"""The uvicorn server the service runs in, with a deadline for request headers.

uvicorn closes idle keep-alive connections but has no limit on how long a client may take
to send its request headers: an idle or trickling connection stays open forever, and with
``limit_concurrency`` enough of them turn every request (health included) into a
text/plain 503. Here a connection must deliver complete headers within
``header_timeout_s`` of opening (or of its previous response), else it is closed; bodies
have their own deadline (:class:`service.limits.BodySizeLimit`) and the number of requests
in progress is bounded by :class:`service.access.AccessGuard` (JSON 503 + Retry-After),
so uvicorn's own connection limit is off.
"""

from __future__ import annotations

import asyncio

import h11
import uvicorn
from uvicorn.protocols.http.h11_impl import H11Protocol

from .config import Settings


class HeaderDeadlineProtocol(H11Protocol):
    """uvicorn's h11 protocol plus a header deadline (``header_timeout`` seconds)."""

    header_timeout: float = 10.0
    _header_timer: asyncio.TimerHandle | None = None

    def _arm(self) -> None:
        self._disarm()
        self._header_timer = self.loop.call_later(self.header_timeout, self._headers_overdue)

    def _disarm(self) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None

    def _headers_overdue(self) -> None:
        self._header_timer = None
        if self.conn.their_state is h11.IDLE and not self.transport.is_closing():
            self.transport.close()

    def connection_made(self, transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm()

    def handle_events(self) -> None:
        super().handle_events()
        if self.conn.their_state is not h11.IDLE:  # the headers are in
            self._disarm()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing() and self.conn.their_state is h11.IDLE:
            self._arm()

    def connection_lost(self, exc) -> None:
        self._disarm()
        super().connection_lost(exc)


def server_config(app, settings: Settings, **kwargs) -> uvicorn.Config:
    """uvicorn config of the service: h11 with the header deadline, no connection-count 503."""
    protocol = type("HeaderDeadline", (HeaderDeadlineProtocol,), {"header_timeout": settings.header_timeout_s})
    kwargs.setdefault("timeout_keep_alive", 30)
    return uvicorn.Config(app, host=settings.host, port=settings.port, http=protocol, limit_concurrency=None,
                          **kwargs)
