"""Who may call, and when: one ASGI middleware in front of the routes.

In order: the Host header must be a trusted name (DNS rebinding), a browser ``Origin``
must be the service itself or a configured CORS origin (a foreign web page cannot POST
scenes), the API key when one is set, and admission: at most ``max_requests`` requests in
progress and a full reconstruction queue refused *before* the upload is read. Every
refusal is the usual JSON error; health and readiness are exempt from auth and admission.
"""

from __future__ import annotations

import hmac
import json
from urllib.parse import unquote_to_bytes, urlsplit

from .config import Settings
from .errors import error_body

#: paths answered whatever the load and without a key (probes, API docs)
OPEN_PATHS = frozenset({"/healthz", "/readyz", "/v2/health/live", "/v2/health/ready", "/docs", "/openapi.json",
                        "/docs/oauth2-redirect", "/redoc"})
#: the POST that queues a reconstruction (admission checked before its body is read)
SCENES_PATH = "/v1/scenes"


def _headers(scope) -> dict[bytes, bytes]:
    return {k.lower(): v for k, v in scope.get("headers", ())}


def _host_name(host: str) -> str:
    """Host header without the port (``[::1]:80`` -> ``[::1]``)."""
    if host.startswith("["):
        return host.split("]")[0] + "]"
    return host.rsplit(":", 1)[0] if host.count(":") == 1 else host


#: the cookie the viewer page sets so that a browser's asset and PLY requests carry the key
KEY_COOKIE = "omnisplat_key"


def _given_key(scope, headers: dict[bytes, bytes]) -> bytes:
    """The API key a request presents: ``Authorization: Bearer``, ``X-API-Key``, the viewer's cookie,
    or (the viewer page only, so a browser can open it) the query parameter ``key``."""
    auth = headers.get(b"authorization", b"")
    if auth[:7].lower() == b"bearer ":
        return auth[7:]
    if b"x-api-key" in headers:
        return headers[b"x-api-key"]
    for part in headers.get(b"cookie", b"").split(b";"):
        name, _, value = part.strip().partition(b"=")
        if name == KEY_COOKIE.encode():
            return value
    if scope.get("method") == "GET" and scope.get("path", "").endswith("/viewer"):
        for part in scope.get("query_string", b"").split(b"&"):
            name, _, value = part.partition(b"=")
            if name == b"key":
                return unquote_to_bytes(value)
    return b""


class AccessGuard:
    """ASGI middleware: trusted hosts, origins, API key, admission (see the module docstring)."""

    def __init__(self, app, settings: Settings, state) -> None:
        self.app = app
        self.state = state
        self.hosts = {h.lower() for h in settings.trusted_hosts}
        self.origins = set(settings.cors_origins)
        self.key = settings.api_key.encode() if settings.api_key else None
        self.max_requests = settings.max_requests
        self.retry_after = settings.retry_after_s
        self.in_flight = 0

    async def _refuse(self, send, status: int, code: str, message: str, headers=()) -> None:
        body = json.dumps(error_body(code, message)).encode()
        await send({"type": "http.response.start", "status": status,
                    "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                                (b"connection", b"close"), *headers]})
        await send({"type": "http.response.body", "body": body})

    def _refusal(self, scope, headers: dict[bytes, bytes]):
        """(status, code, message, extra headers) of a refused request, or None."""
        path = scope.get("path", "")
        host = headers.get(b"host", b"").decode("latin-1").lower()
        if "*" not in self.hosts and _host_name(host) not in self.hosts:
            return 400, "invalid_host", f"Host {host[:100]!r} is not served here", ()
        origin = headers.get(b"origin", b"").decode("latin-1")
        if origin and origin not in self.origins and urlsplit(origin).netloc.lower() != host:
            return 403, "origin_not_allowed", f"requests from the web origin {origin[:100]!r} are not allowed", ()
        if path in OPEN_PATHS:
            return None
        if self.key is not None and scope.get("method") != "OPTIONS":
            given = _given_key(scope, headers)
            if not hmac.compare_digest(given, self.key):
                return 401, "unauthorized", "missing or wrong API key (Authorization: Bearer KEY)", \
                    ((b"www-authenticate", b"Bearer"),)
        retry = ((b"retry-after", str(self.retry_after).encode()),)
        if self.in_flight >= self.max_requests:
            return 503, "busy", f"{self.max_requests} requests in progress; retry in {self.retry_after} s", retry
        if scope.get("method") == "POST" and path.rstrip("/") == SCENES_PATH:
            gate = self.state.inference_gate
            if gate.full:
                gate.reject()
                return 503, "busy", f"reconstruction queue is full; retry in {self.retry_after} s", retry
        return None

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        refusal = self._refusal(scope, _headers(scope))
        if refusal is not None:
            await self._refuse(send, *refusal)
            return
        counted = scope.get("path", "") not in OPEN_PATHS
        self.in_flight += counted
        try:
            await self.app(scope, receive, send)
        finally:
            self.in_flight -= counted
