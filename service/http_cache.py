"""Caching headers of the immutable responses (renders, PLYs) and their conditional requests (RFC 9110).

A scene id is a content hash and a render is a function of the scene, its query and the renderer's code
(:func:`renderer_digest`), so both answers never change while the code does not: they carry
``Cache-Control: immutable`` and an ``ETag``, and a client that sends that
ETag back in ``If-None-Match`` gets ``304 Not Modified`` without the body (and, for a render, without
rendering). Byte ranges are not served: the answers say ``Accept-Ranges: none``.
"""

from __future__ import annotations

import functools
import hashlib
import re
from pathlib import Path

from fastapi import Request, Response

#: ``private``: a shared cache would give an answer to a request with the API key (or the viewer's cookie) to
#: anyone, and keep a deleted scene's files; the browser that asked keeps them
IMMUTABLE = "private, max-age=31536000, immutable"
#: OpenAPI ``responses`` entry of the 304
NOT_MODIFIED = {"description": "Not Modified: `If-None-Match` names this answer's ETag (no body)"}
#: scope key :class:`service.app.HeadAsGet` sets on the GET it runs for a HEAD (a route may then skip the body)
HEAD_SCOPE_KEY = "omnisplat.head"
#: an entity tag in an If-None-Match list: optional weak prefix, then a quoted opaque tag (RFC 9110 section 8.8.3)
_ENTITY_TAG = re.compile(r'\s*(?:W/)?("[^"]*")\s*(?:,|$)')


@functools.cache
def renderer_digest() -> str:
    """A digest of the rasterizer package's sources: a render's ETag changes with the code that draws it."""
    import rasterizer

    root = Path(rasterizer.__file__).parent
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()[:16]


def cache_headers(etag: str) -> dict[str, str]:
    """Headers of a 200 or 304 answer with this (quoted, strong) ``etag``."""
    return {"Cache-Control": IMMUTABLE, "ETag": etag, "Accept-Ranges": "none"}


def etag_matches(if_none_match: str | None, etag: str) -> bool:
    """True when ``If-None-Match`` names ``etag`` (weak comparison: ``W/`` ignored on both) or is ``*``.

    ``etag`` is a quoted tag as sent in the ETag header; the header's tags are read where they parse.
    """
    if not if_none_match:
        return False
    value = if_none_match.strip()
    if value == "*":
        return True
    target = etag[2:] if etag.startswith("W/") else etag
    return any(tag == target for tag in _ENTITY_TAG.findall(value))


def not_modified(request: Request, etag: str) -> Response | None:
    """The 304 answer (no body, the 200's caching headers) when the request's If-None-Match matches, else None."""
    if etag_matches(request.headers.get("if-none-match"), etag):
        return Response(status_code=304, headers=cache_headers(etag))
    return None


def is_head(request: Request) -> bool:
    """True when this GET answers a HEAD: its body is dropped, so a route may skip making it."""
    return bool(request.scope.get(HEAD_SCOPE_KEY))
