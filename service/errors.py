"""Service errors and the one place that maps them (and domain errors) to HTTP responses.

Every error leaves the service as ``{"error": {"code": "...", "message": "..."}}`` with a
status that says whose fault it is: 4xx for every bad input, 503 (+ Retry-After) when busy
or not ready, 500 only for bugs.
"""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from rasterizer.geometry import PoseError

from .encoder import EncoderInputError
from .store import InvalidSceneId, SceneNotFound, StoreCorrupt

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
        return ServiceError(str(exc), code="store_corrupt", status=500)
    if isinstance(exc, EncoderInputError):
        return BadInput(str(exc), code="invalid_input")
    return None


_STATUS_CODES = {400: "bad_request", 404: "not_found", 405: "method_not_allowed", 413: "payload_too_large",
                 415: "unsupported_media_type", 422: "invalid_request", 503: "unavailable"}


def _validation_message(exc: RequestValidationError) -> str:
    parts = []
    for err in exc.errors()[:5]:
        loc = ".".join(str(p) for p in err.get("loc", ()) if p not in ("body", "query", "path"))
        parts.append(f"{loc or 'request'}: {err.get('msg', 'invalid')}")
    return "; ".join(parts) or "invalid request"


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
    async def _http(_: Request, exc: StarletteHTTPException) -> JSONResponse:
        code = _STATUS_CODES.get(exc.status_code, "http_error")
        return error_response(exc.status_code, code, str(exc.detail), getattr(exc, "headers", None))

    @app.exception_handler(Exception)
    async def _unexpected(_: Request, exc: Exception) -> JSONResponse:
        mapped = _domain_error(exc)
        if mapped is not None:
            return error_response(mapped.status, mapped.code, mapped.message, mapped.headers)
        log.exception("unhandled error", exc_info=exc)
        return error_response(500, "internal_error", "internal error; see the service log")


def translate(exc: Exception) -> Exception:
    """The ServiceError for a domain error, else the error itself (used inside worker code)."""
    return _domain_error(exc) or exc
