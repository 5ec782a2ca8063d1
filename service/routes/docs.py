"""``/docs``: the Swagger UI page of the API, with its files served by this service (no CDN, works offline).

The files come from the pinned npm package ``swagger-ui-dist`` (``package.json``, installed with
the viewer's packages by ``npm ci``), under ``/docs/assets/``; only :data:`DOCS_ASSETS` are
served. Without them ``/docs`` answers 503 with our JSON error saying how to install them; the
rest of the API (``/openapi.json`` included) does not depend on them. ReDoc is not served: its
page loads its script and fonts from CDNs.

The page is sent with a Content-Security-Policy (:data:`PAGE_CSP`: its own inline script by hash, no
framing by another site) and ``X-Content-Type-Options: nosniff``, as its files.

``/docs``, its assets and ``/openapi.json`` need no API key, also when one is set (see
:mod:`service.access`): they describe the API only, and a browser opening the page could not
send the key with the page's own request for the schema.
"""

from __future__ import annotations

import re

from fastapi import APIRouter, Request, Response
from fastapi.openapi.docs import get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import FileResponse, HTMLResponse

from ..access import DOCS_ASSETS_PREFIX as ASSETS_PREFIX
from ..errors import NotFound, ServiceError
from .viewer import node_modules_dir, script_hash

router = APIRouter(include_in_schema=False)

#: URL name -> (path inside node_modules, media type)
DOCS_ASSETS = {
    "swagger-ui-bundle.js": ("swagger-ui-dist/swagger-ui-bundle.js", "text/javascript; charset=utf-8"),
    "swagger-ui.css": ("swagger-ui-dist/swagger-ui.css", "text/css; charset=utf-8"),
    "favicon-32x32.png": ("swagger-ui-dist/favicon-32x32.png", "image/png"),
}
_HEADERS = {"Cache-Control": "no-cache", "Referrer-Policy": "no-referrer", "X-Content-Type-Options": "nosniff"}
#: the docs page's Content-Security-Policy (``{inline}``: the hashes of its inline scripts): scripts and requests
#: of this service only, and no framing by another site (its *Try it out* could be clicked through unseen)
PAGE_CSP = ("default-src 'self'; script-src 'self' {inline}; style-src 'self' 'unsafe-inline'; img-src 'self' data:; "
            "connect-src 'self'; object-src 'none'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'")


def missing_docs_assets() -> list[str]:
    """npm files the docs page needs that are not installed."""
    root = node_modules_dir()
    return [rel for rel, _ in DOCS_ASSETS.values() if not (root / rel).is_file()]


def _docs_unavailable() -> ServiceError:
    return ServiceError("the API docs page's npm package (swagger-ui-dist) is not installed: run `npm ci` in the "
                        "repository root (`bash scripts/serve.sh` does); the schema is at /openapi.json "
                        f"(missing npm files: {', '.join(missing_docs_assets())})", code="docs_unavailable", status=503)


@router.get("/docs")
async def docs_page(request: Request) -> HTMLResponse:
    if missing_docs_assets():
        raise _docs_unavailable()
    page = get_swagger_ui_html(openapi_url=request.app.openapi_url, title=f"{request.app.title} - API docs",
                               swagger_js_url=ASSETS_PREFIX + "swagger-ui-bundle.js",
                               swagger_css_url=ASSETS_PREFIX + "swagger-ui.css",
                               swagger_favicon_url=ASSETS_PREFIX + "favicon-32x32.png",
                               oauth2_redirect_url="/docs/oauth2-redirect")
    inline = re.findall(rb"<script>(.*?)</script>", page.body, re.S)
    hashes = " ".join(script_hash(code) for code in inline)
    page.headers.update({**_HEADERS, "Content-Security-Policy": PAGE_CSP.format(inline=hashes),
                         "X-Frame-Options": "DENY"})
    return page


@router.get("/docs/oauth2-redirect")
async def docs_oauth2_redirect() -> HTMLResponse:
    return get_swagger_ui_oauth2_redirect_html()


@router.get(ASSETS_PREFIX + "{name}")
async def docs_asset(name: str) -> Response:
    if name not in DOCS_ASSETS:
        raise NotFound(f"no docs asset {name!r}", code="not_found")
    rel, media = DOCS_ASSETS[name]
    path = node_modules_dir() / rel
    if not path.is_file():
        raise _docs_unavailable()
    return FileResponse(path, media_type=media, headers=_HEADERS)
