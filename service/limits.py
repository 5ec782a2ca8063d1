"""Back-pressure: a request-body cap enforced while streaming, and bounded work queues.

* :class:`BodySizeLimit` is pure ASGI middleware. A declared ``Content-Length`` over the cap
  is refused before any byte reaches the app; a chunked body is counted as it streams in and
  refused the moment it passes the cap (whatever the app answered is replaced by the 413).
  Before answering, the rest of the body is discarded (bounded in bytes and seconds, never
  buffered) so the client reads the 413 rather than a connection reset.
* The same middleware follows a ``multipart/form-data`` body as it streams (:class:`MultipartFraming`,
  nothing kept): a body that ends without its closing boundary is refused (400), since the
  form parser would silently drop its last part, and so is a field sent twice (422 naming it),
  where the parser would silently keep one of them.
* :class:`WorkGate` runs blocking work in worker threads through its own anyio
  ``CapacityLimiter`` (not Starlette's shared pool), with at most ``concurrency`` jobs
  running and ``queue`` waiting; one more is refused at once with 503 + Retry-After.
* :func:`render_cost` prices a render for the 413 render budget and the heavy-render slot.
"""

from __future__ import annotations

import json
from typing import Any, Callable, TypeVar

import anyio
import anyio.to_thread
from python_multipart.multipart import MultipartParseError, MultipartParser, MultipartState, parse_options_header

from .errors import Busy, PayloadTooLarge, error_body, translate

T = TypeVar("T")


#: What one output pixel weighs in :func:`render_cost`, in Gaussians. The renderer's memory is
#: bounded by the image and a depth chunk, not by pixels x Gaussians (rasterizer.front_to_back),
#: but the image's own buffers and maps cost at any scene size: a 4096-wide ERP of one Gaussian
#: takes about 9 CPU s and 0.55 GB (the Yin-Yang merge's taps, made per row block), about what
#: 150k Gaussians cost per pixel on the m3d scene (10.8 CPU s for a 2048-wide ERP of 469k Gaussians).
RENDER_PIXEL_GAUSSIANS = 150_000


def render_cost(height: int, width: int, n_gaussians: int) -> float:
    """A render's cost in pixel-Gaussians: output pixels x (scene Gaussians + :data:`RENDER_PIXEL_GAUSSIANS`).

    Its time grows with the contributions composited (pixels x Gaussians for a given room) and
    with the image's buffers (pixels); compared with ``max_render_cost`` (413 beyond) and
    ``heavy_render_cost`` (the reconstruction slot beyond) of the settings.
    """
    return float(height) * float(width) * (max(int(n_gaussians), 0) + RENDER_PIXEL_GAUSSIANS)


def check_render_budget(height: int, width: int, n_gaussians: int, max_cost: float) -> float:
    """The :func:`render_cost` of a ``width`` x ``height`` render of ``n_gaussians``; 413 ``render_too_large``
    beyond ``max_cost``, with the most pixels this scene may have."""
    cost = render_cost(height, width, n_gaussians)
    if cost > max_cost:
        raise PayloadTooLarge(f"a {width}x{height} render of this scene's {n_gaussians} Gaussians exceeds the render "
                              f"budget ({cost:.3g} > {max_cost:.3g} pixel-Gaussians); ask for at most "
                              f"{int(max_cost // render_cost(1, 1, n_gaussians))} pixels", code="render_too_large")
    return cost


#: longest time, and most bytes (in multiples of the limit), spent discarding an oversize
#: body before answering 413; a client sending more than that sees the connection close
DRAIN_SECONDS = 10.0
DRAIN_LIMITS = 2


class _Refused(Exception):
    def __init__(self, status: int, code: str, message: str) -> None:
        super().__init__(message)
        self.status, self.code, self.message = status, code, message


class MultipartFraming:
    """Follows a multipart/form-data body chunk by chunk: the field names seen and whether the
    closing boundary arrived. ``broken`` when the parser gave up (the form parser reports that)."""

    def __init__(self, boundary: bytes) -> None:
        self.boundary = boundary
        self.names: set[bytes] = set()
        self.duplicate: bytes | None = None
        self.broken = False
        self._field, self._value = bytearray(), bytearray()
        self._name: bytes | None = None

        def field(data, start, end):
            self._field += data[start:end]

        def value(data, start, end):
            self._value += data[start:end]

        def header_end():
            if bytes(self._field).strip().lower() == b"content-disposition":
                _, params = parse_options_header(bytes(self._value))
                self._name = params.get(b"name")
            self._field, self._value = bytearray(), bytearray()

        def headers_finished():
            if self._name is not None:
                if self._name in self.names and self.duplicate is None:
                    self.duplicate = self._name
                self.names.add(self._name)
            self._name = None

        self.parser = MultipartParser(boundary, {"on_header_field": field, "on_header_value": value,
                                                 "on_header_end": header_end, "on_headers_finished": headers_finished})

    @classmethod
    def for_request(cls, scope) -> "MultipartFraming | None":
        """The tracker of a multipart/form-data request with a boundary, else None."""
        for name, value in scope.get("headers", ()):
            if name == b"content-type":
                kind, params = parse_options_header(value)
                if kind == b"multipart/form-data" and params.get(b"boundary"):
                    return cls(params[b"boundary"])
        return None

    def feed(self, chunk: bytes) -> None:
        if chunk and not self.broken:
            try:
                self.parser.write(chunk)
            except MultipartParseError:
                self.broken = True

    @property
    def complete(self) -> bool:
        return self.broken or self.parser.state == MultipartState.END

    def duplicate_refusal(self) -> "_Refused":
        name = self.duplicate.decode("utf-8", "replace")[:100] if self.duplicate else "?"
        return _Refused(422, "duplicate_field", f"form field {name!r} is sent more than once; send each field once")

    def incomplete_refusal(self) -> "_Refused":
        return _Refused(400, "incomplete_multipart", "the multipart body ends without its closing boundary "
                        f"('--{self.boundary.decode('latin-1')[:70]}--'): the upload is incomplete")


class BodySizeLimit:
    """ASGI middleware: 413 JSON error for request bodies over ``max_bytes``; 408 for bodies that
    take longer than ``timeout_s`` to arrive, or that arrive slower than ``min_rate`` bytes/s.

    The rate is measured in windows of ``rate_window_s`` seconds of *waiting* for the body (time
    the app spends between reads does not count against the client): each window must bring
    ``min_rate * rate_window_s`` bytes, or the rest of a body whose ``Content-Length`` says it
    is shorter. A client trickling its upload is cut off after one window, not after the whole
    ``timeout_s``, so slow clients cannot hold the upload slots of :class:`service.access.AccessGuard`.
    """

    def __init__(self, app, max_bytes: int, on_reject: Callable[[], None] | None = None,
                 timeout_s: float = 120.0, min_rate: float = 0.0, rate_window_s: float = 10.0) -> None:
        self.app = app
        self.max_bytes = max_bytes
        self.on_reject = on_reject
        self.timeout_s = timeout_s
        self.min_rate = min_rate
        self.rate_window_s = rate_window_s

    async def _drain(self, receive) -> None:
        """Read and discard what the client is still sending, at most ``DRAIN_LIMITS`` limits' worth
        and for at most ``DRAIN_SECONDS``: closing with unread data resets the connection,
        and the client would see that instead of the 413. Nothing is kept in memory."""
        budget = DRAIN_LIMITS * self.max_bytes
        with anyio.move_on_after(DRAIN_SECONDS):
            while budget > 0:
                message = await receive()
                if message["type"] != "http.request":
                    return
                budget -= len(message.get("body", b""))
                if not message.get("more_body", False):
                    return

    async def _reject(self, send, refused: _Refused) -> None:
        if self.on_reject is not None and refused.status == 413:
            self.on_reject()
        body = json.dumps(error_body(refused.code, refused.message)).encode()
        await send({"type": "http.response.start", "status": refused.status,
                    "headers": [(b"content-type", b"application/json"),
                                (b"content-length", str(len(body)).encode()), (b"connection", b"close")]})
        await send({"type": "http.response.body", "body": body})

    def _too_large(self) -> _Refused:
        return _Refused(413, "payload_too_large", f"request body exceeds the limit of {self.max_bytes} bytes")

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared: int | None = None
        for name, value in scope.get("headers", ()):
            if name == b"content-length":
                try:
                    declared = int(value)
                except ValueError:
                    declared = -1
                if declared > self.max_bytes:
                    await self._drain(receive)
                    await self._reject(send, self._too_large())
                    return
        received = 0
        refused: _Refused | None = None
        started = False
        body_done = False
        framing = MultipartFraming.for_request(scope)
        deadline = anyio.current_time() + self.timeout_s
        window = self.rate_window_s
        window_waited = 0.0  # seconds spent waiting for the body in the current rate window
        window_bytes = 0  # received in it

        def too_slow() -> _Refused:
            return _Refused(408, "request_timeout", f"the request body arrived slower than {self.min_rate:g} bytes/s "
                                                    f"(measured over {window:g} s)")

        def window_ok() -> bool:
            need = self.min_rate * window
            if declared is not None and declared >= 0:
                need = min(need, declared - (received - window_bytes))  # the rest of the body, at the window's start
            return window_bytes >= need

        async def counting_receive():
            nonlocal received, refused, body_done, window_waited, window_bytes
            if body_done:  # after the body: disconnect polling, no deadline
                return await receive()
            while True:
                now = anyio.current_time()
                wait = deadline - now
                if self.min_rate > 0:
                    wait = min(wait, window - window_waited)
                try:
                    with anyio.fail_after(max(0.0, wait)):
                        message = await receive()
                    window_waited += anyio.current_time() - now
                    break
                except TimeoutError:
                    window_waited += anyio.current_time() - now
                    if anyio.current_time() >= deadline:
                        refused = _Refused(408, "request_timeout",
                                           f"the request body did not arrive within {self.timeout_s:g} s")
                        raise refused from None
                    if not window_ok():
                        refused = too_slow()
                        raise refused from None
                    window_waited, window_bytes = 0.0, 0  # this window brought enough: the next one
            if message["type"] == "http.request":
                size = len(message.get("body", b""))
                received += size
                window_bytes += size
                body_done = not message.get("more_body", False)
                if received > self.max_bytes:
                    refused = self._too_large()
                    raise refused
                if framing is not None:
                    framing.feed(message.get("body", b""))
                    if framing.duplicate is not None:
                        refused = framing.duplicate_refusal()
                        raise refused
                    if body_done and not framing.complete:
                        refused = framing.incomplete_refusal()
                        raise refused
                if not body_done and self.min_rate > 0 and window_waited >= window:
                    if not window_ok():
                        refused = too_slow()
                        raise refused
                    window_waited, window_bytes = 0.0, 0
            return message

        async def guarded_send(message):
            nonlocal started
            if refused is not None:  # the app reacted to the refusal in its own way: answer it instead
                return
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, counting_receive, guarded_send)
        except _Refused:
            pass
        except Exception:
            if refused is None:
                raise
        if refused is not None and not started:
            if refused.status != 408 and not body_done:  # the client still sends: read it, then answer
                await self._drain(receive)
            await self._reject(send, refused)


class WorkGate:
    """Bounded thread-pool access for one kind of heavy work (inference, rendering)."""

    def __init__(self, name: str, concurrency: int, queue: int, retry_after: int,
                 on_reject: Callable[[], None] | None = None, limiter: anyio.CapacityLimiter | None = None) -> None:
        self.name = name
        self.on_reject = on_reject
        self.concurrency = concurrency
        self.queue = queue
        self.retry_after = retry_after
        self.limiter = limiter or anyio.CapacityLimiter(concurrency)
        self.admitted = 0  # running + waiting; only touched on the event loop thread
        self.rejected = 0

    @property
    def running(self) -> int:
        return int(self.limiter.borrowed_tokens)

    @property
    def waiting(self) -> int:
        return max(0, self.admitted - self.running)

    @property
    def full(self) -> bool:
        """True when one more job would be refused."""
        return self.admitted >= self.concurrency + self.queue

    def reject(self) -> None:
        """Count a refusal (also for one refused before its request body was read)."""
        self.rejected += 1
        if self.on_reject is not None:
            self.on_reject()

    async def run(self, fn: Callable[..., T], *args: Any) -> T:
        """Run ``fn(*args)`` in a worker thread, or raise :class:`Busy` if the queue is full."""
        if self.full:
            self.reject()
            raise Busy(f"{self.name} queue is full ({self.concurrency} running, {self.queue} waiting); "
                       f"retry in {self.retry_after} s", retry_after=self.retry_after, code="busy")
        self.admitted += 1
        try:
            return await anyio.to_thread.run_sync(_translated, fn, args, limiter=self.limiter)
        finally:
            self.admitted -= 1


def _translated(fn: Callable[..., T], args: tuple) -> T:
    try:
        return fn(*args)
    except Exception as exc:  # domain errors leave the worker as ServiceErrors
        mapped = translate(exc)
        if mapped is exc:
            raise
        raise mapped from exc
