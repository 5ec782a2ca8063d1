"""Service errors and the one place that maps them (and domain errors) to HTTP responses.

Every error leaves the service as ``{"error": {"code": "...", "message": "..."}}`` with a
status that says whose fault it is: 4xx for every bad input, 503 (+ Retry-After) when busy
or not ready, 500 only for bugs.
"""

from __future__ import annotations

import errno
import json
import logging
import sys

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.datastructures import UploadFile as StarletteUploadFile
from starlette.exceptions import HTTPException as StarletteHTTPException

from rasterizer.geometry import PoseError
from rasterizer.splat import RenderLimitError

from .encoder import EncoderInputError
from .store import InvalidSceneId, SceneNotFound, StoreCorrupt, StoreFull, StoreInterrupted

log = logging.getLogger("omnisplat.service")


class ServiceError(Exception):
    """An error with an HTTP status and a stable machine-readable code."""

    status = 400
    code = "bad_request"

    def __init__(self, message: str, *, code: str | None = None, status: int | None = None,
                 headers: dict[str, str] | None = None) -> None:
        super().__init__(message)
        self.message = message
        if code is not None:
            self.code = code
        if status is not None:
            self.status = status
        self.headers = headers or {}


class BadInput(ServiceError):
    status = 422
    code = "invalid_input"


class InvalidImage(ServiceError):
    status = 400
    code = "invalid_image"


class PayloadTooLarge(ServiceError):
    status = 413
    code = "payload_too_large"


class NotFound(ServiceError):
    status = 404
    code = "not_found"


class Busy(ServiceError):
    status = 503
    code = "busy"

    def __init__(self, message: str, *, retry_after: int, code: str | None = None) -> None:
        super().__init__(message, code=code, headers={"Retry-After": str(int(retry_after))})


class StoreUnavailable(ServiceError):
    """The scene store cannot take writes (disk full, read-only, permissions)."""

    status = 507
    code = "store_unavailable"


#: OSError numbers that mean "the store's disk cannot take this write", not a bug
STORE_ERRNOS = {errno.ENOSPC: "the scene store's disk is full", errno.EDQUOT: "the scene store's disk quota is used up",
                errno.EROFS: "the scene store is on a read-only file system",
                errno.EACCES: "the scene store is not writable", errno.EPERM: "the scene store is not writable"}


def error_body(code: str, message: str) -> dict:
    return {"error": {"code": code, "message": message}}


def error_response(status: int, code: str, message: str, headers: dict[str, str] | None = None) -> JSONResponse:
    return JSONResponse(error_body(code, message), status_code=status, headers=headers)


def _domain_error(exc: Exception) -> ServiceError | None:
    """Translate an error raised by rasterizer/encoder code into a ServiceError (None: a bug)."""
    if isinstance(exc, ServiceError):
        return exc
    if isinstance(exc, PoseError):
        return BadInput(str(exc), code="invalid_pose")
    if isinstance(exc, InvalidSceneId):
        return BadInput(str(exc), code="invalid_scene_id")
    if isinstance(exc, SceneNotFound):
        return NotFound(str(exc), code="scene_not_found")
    if isinstance(exc, StoreCorrupt):
        log.error("%s", exc)
        return ServiceError(f"{exc}; the scene's stored files are damaged: POST its images again to build it anew, or "
                            "DELETE it", code="store_corrupt", status=500)
    if isinstance(exc, EncoderInputError):
        return BadInput(str(exc), code="invalid_input")
    if isinstance(exc, RenderLimitError):
        return PayloadTooLarge(f"render too large for this scene: {exc}", code="render_too_large")
    if isinstance(exc, StoreFull):  # a store limit (budget, scene count, free-disk margin): its message says which
        return StoreUnavailable(exc.message, code=exc.code)
    if isinstance(exc, StoreInterrupted):  # another process kept clearing the staging folder: send it again
        log.warning("%s", exc)
        return Busy(exc.message, retry_after=1, code=exc.code)
    if isinstance(exc, OSError) and exc.errno in STORE_ERRNOS:
        log.error("store write failed: %s", exc)
        return StoreUnavailable(f"{STORE_ERRNOS[exc.errno]}; the request was not stored", code="store_unavailable")
    return None


#: errors raised by rasterizer/encoder/store code that :func:`_domain_error` translates
DOMAIN_ERRORS = (InvalidSceneId, SceneNotFound, StoreCorrupt, EncoderInputError, RenderLimitError, OSError)

_STATUS_CODES = {400: "bad_request", 404: "not_found", 405: "method_not_allowed", 413: "payload_too_large",
                 415: "unsupported_media_type", 422: "invalid_request", 503: "unavailable"}


def _json_kind(value) -> str:
    """What a JSON body holds, in JSON's words (a body that is not an object)."""
    kinds = ((bool, "true or false"), (list, "an array"), (str, "a string"), ((int, float), "a number"),
             (bytes, "a body that is not JSON"))
    return next((name for kind, name in kinds if isinstance(value, kind)), "null" if value is None else "no object")


def _validation_message(exc: RequestValidationError) -> str:
    parts = []
    for err in exc.errors()[:5]:
        if err.get("type") == "json_invalid":  # loc is ("body", character offset)
            where = err.get("loc", ("body", "?"))[-1]
            reason = (err.get("ctx") or {}).get("error", "")
            parts.append(f"body: not valid JSON at character {where}" + (f" ({reason})" if reason else ""))
            continue
        loc = ".".join(str(p) for p in err.get("loc", ()) if p not in ("body", "query", "path"))
        if not loc and err.get("type") in ("model_attributes_type", "dict_type", "model_type"):
            parts.append(f"request body: expected a JSON object, got {_json_kind(err.get('input'))}")
            continue
        msg = str(err.get("msg", "invalid")).removeprefix("Value error, ")  # a validator's own words
        if "Expected UploadFile" in msg:  # a form field where a file was expected (the library's words)
            msg = "expected a file (a form part with a filename), got a text field"
        elif err.get("type") == "string_type" and isinstance(err.get("input"), StarletteUploadFile):
            msg = "expected a text field, got a file"
        parts.append(f"{loc or 'request'}: {msg}")
    return "; ".join(parts) or "invalid request"


def body_parse_fault(cause: BaseException | None) -> str | None:
    """Why FastAPI's parser refused a JSON body ("There was an error parsing the body"), in the user's terms, from
    the error it raised: nested too deeply, an integer longer than Python converts (its own words name its
    settings), or bytes that are not UTF-8 text; None for any other cause (a form's, the upload limits')."""
    if isinstance(cause, RecursionError):
        return "arrays or objects nested too deeply"
    if isinstance(cause, UnicodeDecodeError):
        return f"not UTF-8 text ({cause.reason} at byte {cause.start})"
    if isinstance(cause, ValueError) and not isinstance(cause, json.JSONDecodeError) and "digits" in str(cause):
        return f"an integer of more than {sys.get_int_max_str_digits()} digits"  # Python's own limit, as parsed
    return None


def _allowed_methods(request: Request) -> str | None:
    """Allow header of a 405: the methods of every route matching the path (not only the first)."""
    from starlette.routing import Match

    def leaves(routes):
        for route in routes:
            sub = getattr(route, "original_router", None)  # FastAPI's included routers
            yield from leaves(sub.routes) if sub is not None else (route,)

    methods: set[str] = set()
    for route in leaves(request.app.router.routes):
        match, _ = route.matches(request.scope)
        if match is not Match.NONE:
            methods |= set(getattr(route, "methods", None) or ())
    return ", ".join(sorted(methods)) or None


def install_error_handlers(app: FastAPI) -> None:
    """Register the handlers; call once from create_app."""

    @app.exception_handler(ServiceError)
    async def _service_error(_: Request, exc: ServiceError) -> JSONResponse:
        return error_response(exc.status, exc.code, exc.message, exc.headers)

    @app.exception_handler(PoseError)
    async def _pose_error(_: Request, exc: PoseError) -> JSONResponse:
        return error_response(422, "invalid_pose", str(exc))

    @app.exception_handler(RequestValidationError)
    async def _validation(_: Request, exc: RequestValidationError) -> JSONResponse:
        return error_response(422, "invalid_request", _validation_message(exc))

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        code = _STATUS_CODES.get(exc.status_code, "http_error")
        headers = dict(getattr(exc, "headers", None) or {})
        if exc.status_code == 405:
            allow = _allowed_methods(request)
            if allow:
                headers["Allow"] = allow
        if exc.status_code == 400 and str(exc.detail).startswith(("Part exceeded maximum size", "Field exceeded")):
            return error_response(413, "form_field_too_large", f"a text form field is too large ({exc.detail}): "
                                  "poses and options are small JSON objects; images go as files")
        if exc.status_code == 400 and "parsing the body" in str(exc.detail):  # one status for a malformed body
            fault = body_parse_fault(exc.__cause__)  # the body is not read again: a form's may be half read
            if fault:
                return error_response(422, "invalid_request", f"request body: not valid JSON ({fault})")
            return error_response(422, "invalid_request", f"the request body could not be parsed ({exc.detail})")
        return error_response(exc.status_code, code, str(exc.detail), headers or None)

    async def _domain(_: Request, exc: Exception) -> JSONResponse:
        mapped = _domain_error(exc)
        if mapped is None:
            raise exc  # a bug after all (e.g. another OSError): the 500 handler below
        return error_response(mapped.status, mapped.code, mapped.message, mapped.headers)

    # Handled by class (inside the app), not by the catch-all below: Starlette re-raises what the
    # catch-all answered, and the server then drops the keep-alive connection.
    for domain_type in DOMAIN_ERRORS:
        app.add_exception_handler(domain_type, _domain)

    @app.exception_handler(Exception)
    async def _unexpected(_: Request, exc: Exception) -> JSONResponse:
        mapped = _domain_error(exc)
        if mapped is not None:
            return error_response(mapped.status, mapped.code, mapped.message, mapped.headers)
        log.exception("unhandled error", exc_info=exc)
        # Starlette re-raises after this answer and the server then closes the connection: say so, so that
        # a pooled or pipelining client does not send its next request into a closing connection
        return error_response(500, "internal_error", "internal error; see the service log", {"Connection": "close"})


def translate(exc: Exception) -> Exception:
    """The ServiceError for a domain error, else the error itself (used inside worker code)."""
    return _domain_error(exc) or exc
