"""The uvicorn server the service runs in: a header deadline, JSON protocol errors, and a lingering close.

uvicorn closes idle keep-alive connections but has no limit on how long a client may take
to send its request headers: an idle or trickling connection stays open forever, and with
``limit_concurrency`` enough of them turn every request (health included) into a
text/plain 503. Here a connection must deliver complete headers within
``header_timeout_s`` of opening (or of its previous response), else it is closed; bodies
have their own deadline and minimum rate (:class:`service.limits.BodySizeLimit`) and the
number of requests in progress is bounded by :class:`service.access.AccessGuard` (JSON
503 + Retry-After), so uvicorn's own connection limit is off.

Requests h11 cannot parse are answered in the service's JSON error shape with the status
h11 suggests (431 for headers over ``max_header_bytes``, else 400), and so is a request
carrying both ``Content-Length`` and ``Transfer-Encoding`` (behind a proxy that reads the
other header, that is request smuggling; RFC 9112 section 6.1 lets a server refuse it). After
such an answer the connection shuts its sending side and discards what the client is still
sending, for at most :data:`LINGER_SECONDS` and :data:`LINGER_BYTES`, before closing: closing
with unread data makes the kernel send a reset, and the client would see that instead of
the answer.

The access log (``uvicorn.access``) never shows the viewer's ``key`` query parameter: it is
replaced by ``key=<redacted>`` (:class:`RedactKeyFilter`).
"""

from __future__ import annotations

import asyncio
import json
import logging
import re

import h11
import uvicorn
from uvicorn.protocols.http.h11_impl import H11Protocol

from .config import Settings
from .errors import error_body

#: after refusing a request the server cannot parse, how long (s) and how many bytes it reads and
#: discards before closing, so that the client sees the answer instead of a reset
LINGER_SECONDS = 2.0
LINGER_BYTES = 4 * 1024 * 1024

_PROTOCOL_CODES = {431: ("header_too_large", "request headers too large"),
                   400: ("bad_request", "malformed HTTP request"),
                   501: ("not_implemented", "unsupported HTTP feature")}


class _Connection(h11.Connection):
    """h11's server-side connection; keeps the last protocol error and refuses CL + TE together."""

    refusal: h11.RemoteProtocolError | None = None

    def next_event(self):  # type: ignore[override]
        try:
            event = super().next_event()
        except h11.RemoteProtocolError as exc:
            self.refusal = exc
            raise
        if isinstance(event, h11.Request):
            names = {name.lower() for name, _ in event.headers}
            if b"transfer-encoding" in names and b"content-length" in names:
                self.refusal = h11.RemoteProtocolError(
                    "a request must not carry both Content-Length and Transfer-Encoding", error_status_hint=400)
                raise self.refusal
        return event


class HeaderDeadlineProtocol(H11Protocol):
    """uvicorn's h11 protocol plus a header deadline (``header_timeout`` seconds), JSON protocol
    errors (``max_header_bytes`` in the 431 message) and a lingering close after them."""

    header_timeout: float = 10.0
    max_header_bytes: int = 16 * 1024  # h11's default
    _header_timer: asyncio.TimerHandle | None = None
    _lingering: int | None = None  # bytes discarded since the refusal (None: not lingering)

    def __init__(self, config, *args, **kwargs) -> None:
        super().__init__(config, *args, **kwargs)
        self.conn = _Connection(h11.SERVER, config.h11_max_incomplete_event_size or self.max_header_bytes)

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

    def data_received(self, data: bytes) -> None:
        if self._lingering is not None:  # after a refusal: read and drop, bounded
            self._lingering += len(data)
            if self._lingering > LINGER_BYTES:
                self.transport.close()
            return
        super().data_received(data)

    def handle_events(self) -> None:
        super().handle_events()
        if self.conn.their_state is not h11.IDLE:  # the headers are in
            self._disarm()

    def send_400_response(self, msg: str) -> None:
        """Answer a request h11 refused (or :class:`_Connection` did) as JSON, then linger and close."""
        exc = self.conn.refusal
        status = getattr(exc, "error_status_hint", 400) if exc is not None else 400
        code, what = _PROTOCOL_CODES.get(status, ("bad_request", "malformed HTTP request"))
        if status == 431:
            detail = f"{what}: at most {self.max_header_bytes} bytes of request line and headers"
        else:
            detail = f"{what}: {exc}" if exc is not None and str(exc) else what
        body = json.dumps(error_body(code, detail)).encode()
        self._disarm()
        try:
            for event in (h11.Response(status_code=status, reason=_reason(status),
                                       headers=[(b"content-type", b"application/json"),
                                                (b"content-length", str(len(body)).encode()),
                                                (b"connection", b"close")]),
                          h11.Data(data=body), h11.EndOfMessage()):
                self.transport.write(self.conn.send(event))
        except h11.LocalProtocolError:  # a response is already under way: nothing more can be said
            self.transport.close()
            return
        self._lingering = 0
        if self.transport.can_write_eof():
            self.transport.write_eof()
        self.loop.call_later(LINGER_SECONDS, self.transport.close)

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing() and self.conn.their_state is h11.IDLE:
            self._arm()

    def connection_lost(self, exc) -> None:
        self._disarm()
        super().connection_lost(exc)


def _reason(status: int) -> bytes:
    from http import HTTPStatus

    try:
        return HTTPStatus(status).phrase.encode()
    except ValueError:
        return b""


#: a ``key`` query parameter as sent: the name may be percent-encoded (``%6Bey``, which the guard reads as
#: ``key``) or in capitals (not the key parameter, but a key all the same)
_KEY_PARAM = re.compile(r"(?<=[?&])(?:k|%[46]b)(?:e|%[46]5)(?:y|%[57]9)=[^&\s\"]*", re.IGNORECASE)


class RedactKeyFilter(logging.Filter):
    """Replaces the value of a ``key`` query parameter in access-log records with ``<redacted>``."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.args, tuple) and any(isinstance(a, str) and "=" in a for a in record.args):
            record.args = tuple(_KEY_PARAM.sub("key=<redacted>", a) if isinstance(a, str) else a for a in record.args)
        return True


def server_config(app, settings: Settings, **kwargs) -> uvicorn.Config:
    """uvicorn config of the service: h11 with the header deadline, no connection-count 503."""
    protocol = type("HeaderDeadline", (HeaderDeadlineProtocol,), {"header_timeout": settings.header_timeout_s,
                                                                  "max_header_bytes": settings.max_header_bytes})
    kwargs.setdefault("timeout_keep_alive", 30)
    config = uvicorn.Config(app, host=settings.host, port=settings.port, http=protocol, limit_concurrency=None,
                            h11_max_incomplete_event_size=settings.max_header_bytes, **kwargs)
    access = logging.getLogger("uvicorn.access")  # after Config, which configures logging
    if not any(isinstance(f, RedactKeyFilter) for f in access.filters):
        access.addFilter(RedactKeyFilter())
    return config
