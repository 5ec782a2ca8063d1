"""Who may call, and when: one ASGI middleware in front of the routes.

In order: the Host header must be a trusted name (DNS rebinding), a browser ``Origin``
must be the service itself or a configured CORS origin (a foreign web page cannot POST
scenes), the API key when one is set, and admission. Every refusal is the usual JSON
error; health and readiness are exempt from auth and admission.

Admission counts two kinds of slots (:class:`Admission`): a request whose body is still
arriving holds a *reader* slot (at most ``max_body_readers``), any other request a *work*
slot (at most ``max_requests``); a request moves from the first to the second when its
body has arrived. A flood of slow uploads therefore fills the reader slots only (and
:class:`service.limits.BodySizeLimit` cuts each off below the minimum body rate), while
renders, metadata and info keep their own slots. A request with a body is refused at once
when its reader slots or the work slots are full, and a full reconstruction queue refuses
``POST /v1/scenes`` before its upload is read. ``/readyz`` reports full slots.

The API docs (``/docs``, its assets under ``/docs/assets/``, ``/openapi.json``) need no key,
also when one is set: they describe the API, as the public code does, and hold no scene,
setting or path; and a browser opening ``/docs`` cannot send a header with its own request
for the schema (Swagger UI's *Authorize* then sends the key with the calls it makes).
"""

from __future__ import annotations

import hmac
import json
from urllib.parse import unquote_to_bytes, urlsplit

from .config import Settings
from .errors import error_body

#: paths answered whatever the load and without a key (probes, API docs)
OPEN_PATHS = frozenset({"/healthz", "/readyz", "/v2/health/live", "/v2/health/ready", "/docs", "/openapi.json",
                        "/docs/oauth2-redirect"})
#: path prefix of the API docs' own files (open as the docs page is)
DOCS_ASSETS_PREFIX = "/docs/assets/"
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


def is_open(path: str) -> bool:
    """True for the paths answered without a key and outside admission (probes, API docs)."""
    return path in OPEN_PATHS or path.startswith(DOCS_ASSETS_PREFIX)


def declare_auth(schema: dict) -> dict:
    """The OpenAPI ``schema`` with the key every path outside :func:`is_open` may ask for: a bearer security
    scheme (optional: only a server started with an API key checks it) and a 401 answer with the JSON error."""
    components = schema.setdefault("components", {})
    components.setdefault("securitySchemes", {})["apiKey"] = {
        "type": "http", "scheme": "bearer",
        "description": "Only when the server has OMNISPLAT_API_KEY: `Authorization: Bearer KEY` (or `X-API-Key`)"}
    error = {"$ref": "#/components/schemas/ErrorResponse"}
    for path, operations in schema.get("paths", {}).items():
        if is_open(path):
            continue
        for operation in operations.values():
            operation.setdefault("security", [{}, {"apiKey": []}])  # {}: no key needed when none is set
            operation.setdefault("responses", {}).setdefault("401", {
                "description": "Missing or wrong API key (only when the server has one)",
                "content": {"application/json": {"schema": error}}})
    return schema


class DuplicateKey(ValueError):
    """The query names ``key`` more than once."""


def query_key(scope) -> bytes | None:
    """The viewer page's ``key`` query parameter (None: absent); :class:`DuplicateKey` when given twice."""
    found = [value for name, _, value in (part.partition(b"=") for part in scope.get("query_string", b"").split(b"&"))
             if unquote_to_bytes(name) == b"key"]
    if len(found) > 1:
        raise DuplicateKey("the query parameter 'key' is given more than once; give it once")
    return unquote_to_bytes(found[0].replace(b"+", b" ")) if found else None


def is_viewer_page(scope) -> bool:
    return scope.get("method") in ("GET", "HEAD") and scope.get("path", "").endswith("/viewer")


def _given_key(scope, headers: dict[bytes, bytes]) -> bytes:
    """The API key a request presents: ``Authorization: Bearer``, ``X-API-Key``, the viewer's cookie (percent-encoded),
    or (the viewer page only, so a browser can open it) the query parameter ``key``, which wins over
    the cookie there (the page then replaces the cookie with it)."""
    auth = headers.get(b"authorization", b"")
    if auth[:7].lower() == b"bearer ":
        return auth[7:]
    if b"x-api-key" in headers:
        return headers[b"x-api-key"]
    if is_viewer_page(scope):
        key = query_key(scope)
        if key is not None:
            return key
    for part in headers.get(b"cookie", b"").split(b";"):
        name, _, value = part.strip().partition(b"=")
        if name == KEY_COOKIE.encode():
            return unquote_to_bytes(value)  # the viewer page sets it percent-encoded
    return b""


def has_body(headers: dict[bytes, bytes]) -> bool:
    """True when the request announces a body (a non-zero Content-Length, or chunked)."""
    if b"transfer-encoding" in headers:
        return True
    return headers.get(b"content-length", b"0").strip() not in (b"0", b"")


class Admission:
    """The two kinds of request slots (see the module docstring); only touched on the event loop."""

    def __init__(self, max_requests: int, max_body_readers: int) -> None:
        self.max_requests = max_requests
        self.max_body_readers = max_body_readers
        self.working = 0
        self.reading = 0

    def problem(self) -> str | None:
        """Why no more work can be taken now (None: it can)."""
        if self.working >= self.max_requests:
            return f"busy: all {self.max_requests} request slots are in use"
        if self.reading >= self.max_body_readers:
            return f"busy: all {self.max_body_readers} upload slots are in use (request bodies arriving)"
        return None


class _SlotsFull(Exception):
    """Raised from ``receive`` when a body has arrived but no work slot is free."""


class AccessGuard:
    """ASGI middleware: trusted hosts, origins, API key, admission (see the module docstring)."""

    def __init__(self, app, settings: Settings, state) -> None:
        self.app = app
        self.state = state
        self.hosts = {h.lower() for h in settings.trusted_hosts}
        self.origins = set(settings.cors_origins)
        self.key = settings.api_key.encode() if settings.api_key else None
        self.admission = getattr(state, "admission", None) or Admission(settings.max_requests,
                                                                         settings.max_body_readers)
        self.retry_after = settings.retry_after_s

    async def _refuse(self, send, status: int, code: str, message: str, headers=()) -> None:
        body = json.dumps(error_body(code, message)).encode()
        await send({"type": "http.response.start", "status": status,
                    "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                                (b"connection", b"close"), *headers]})
        await send({"type": "http.response.body", "body": body})

    def _busy(self, message: str):
        return 503, "busy", f"{message}; retry in {self.retry_after} s", ((b"retry-after", str(self.retry_after).encode()),)

    def _refusal(self, scope, headers: dict[bytes, bytes]):
        """(status, code, message, extra headers) of a refused request, or None."""
        path = scope.get("path", "")
        host = headers.get(b"host", b"").decode("latin-1").lower()
        if "*" not in self.hosts and _host_name(host) not in self.hosts:
            return 400, "invalid_host", f"Host {host[:100]!r} is not served here", ()
        origin = headers.get(b"origin", b"").decode("latin-1")
        if origin and origin not in self.origins and urlsplit(origin).netloc.lower() != host:
            return 403, "origin_not_allowed", f"requests from the web origin {origin[:100]!r} are not allowed", ()
        if is_open(path):
            return None
        if self.key is not None and scope.get("method") != "OPTIONS":
            try:
                given = _given_key(scope, headers)
            except DuplicateKey as exc:
                return 400, "duplicate_query_parameter", str(exc), ()
            if not hmac.compare_digest(given, self.key):
                return 401, "unauthorized", "missing or wrong API key (Authorization: Bearer KEY)", \
                    ((b"www-authenticate", b"Bearer"),)
        slots = self.admission
        if slots.working >= slots.max_requests:
            return self._busy(f"{slots.max_requests} requests in progress")
        if has_body(headers) and slots.reading >= slots.max_body_readers:
            return self._busy(f"{slots.max_body_readers} uploads in progress")
        if scope.get("method") == "POST" and path.rstrip("/") == SCENES_PATH:
            gate = self.state.inference_gate
            if gate.full:
                gate.reject()
                return self._busy("reconstruction queue is full")
        return None

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = _headers(scope)
        refusal = self._refusal(scope, headers)
        if refusal is not None:
            await self._refuse(send, *refusal)
            return
        if is_open(scope.get("path", "")):
            await self.app(scope, receive, send)
            return
        slots = self.admission
        phase = "reading" if has_body(headers) else "working"
        setattr(slots, phase, getattr(slots, phase) + 1)
        refused = False
        started = False

        async def admitted_receive():
            nonlocal phase, refused
            message = await receive()
            if phase == "reading" and (message["type"] != "http.request" or not message.get("more_body", False)):
                slots.reading -= 1  # the body is in (or the client left): a work slot now
                phase = "done"
                if message["type"] == "http.request" and slots.working >= slots.max_requests:
                    refused = True
                    raise _SlotsFull
                slots.working += 1
                phase = "working"
            return message

        async def guarded_send(message):
            nonlocal started
            if refused:  # the app answered the refusal in its own way: ours is sent instead
                return
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, admitted_receive, guarded_send)
        except Exception:
            if not refused:
                raise
        finally:
            if phase in ("reading", "working"):
                setattr(slots, phase, getattr(slots, phase) - 1)
        if refused and not started:
            await self._refuse(send, *self._busy(f"{slots.max_requests} requests in progress"))
