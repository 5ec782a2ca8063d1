"""``/v1/scenes/{id}/viewer``: a web 3DGS viewer page (GaussianSplats3D + three.js) for a scene.

The viewer's JavaScript comes from npm (``package.json`` / ``package-lock.json`` at the repository
root, installed by ``npm ci``) and is served from ``node_modules`` by this service under
``/viewer-assets/``: no CDN, works offline. Only the files listed in :data:`NPM_ASSETS` and our own
page files in ``service/viewer/`` are served. Without them the page answers 503 with our JSON error
shape saying how to install them; the rest of the API does not depend on them.

The page and its assets are sent with cross-origin isolation headers (COOP/COEP), which the
viewer's sort worker needs for SharedArrayBuffer, ``Referrer-Policy: no-referrer`` and
``X-Content-Type-Options: nosniff``; the page also with a Content-Security-Policy (:data:`PAGE_CSP`)
that refuses framing by another site.

A browser cannot send the API key as a header, so the page takes it once as ``?key=``: the
answer is a 303 to the same URL without it, setting a same-site, HTTP-only cookie that the
page's later requests (the redirect's target, assets, PLY) carry. The key thus leaves the
address bar at once, and the access log shows it redacted (:mod:`service.server`); but a browser's
history keeps the URL as it was opened (Chromium records a redirect's first URL as a visit), so a
shared or synced browser profile holds the key (docs/operations.md).
"""

from __future__ import annotations

import base64
import hashlib
import html
import json
import logging
import math
import os
import re
from pathlib import Path
from typing import Annotated, Literal
from urllib.parse import quote, urlencode

import anyio.to_thread
from fastapi import APIRouter, Query, Request, Response
from fastapi.responses import FileResponse, HTMLResponse, RedirectResponse

from ..access import KEY_COOKIE, DuplicateKey, query_key
from ..deps import KnownQueryParameters, SceneId, SettingsDep, SingleQueryValues, StoreDep
from ..errors import BadInput, NotFound, ServiceError
from ..inputs import DEFAULT_FOV_DEG, PLAIN_DECIMAL, check_camera_reach, check_fov, parse_c2w_query
from ..schemas import error_responses

router = APIRouter(tags=["viewer"], dependencies=[KnownQueryParameters, SingleQueryValues])
log = logging.getLogger("omnisplat.service")

REPO_ROOT = Path(__file__).resolve().parents[2]
PAGE_DIR = Path(__file__).resolve().parents[1] / "viewer"

#: URL name -> path inside node_modules (the only npm files served).
NPM_ASSETS = {
    "three.module.js": "three/build/three.module.js",
    "three.core.js": "three/build/three.core.js",
    "gaussian-splats-3d.module.js": "@mkkellogg/gaussian-splats-3d/build/gaussian-splats-3d.module.js",
}
#: our own page files (service/viewer/)
PAGE_ASSETS = {"viewer.js": "viewer.js", "viewer.css": "viewer.css"}

ISOLATION_HEADERS = {
    "Cross-Origin-Opener-Policy": "same-origin",
    "Cross-Origin-Embedder-Policy": "require-corp",
    "Cross-Origin-Resource-Policy": "same-origin",
    "Referrer-Policy": "no-referrer",
    "X-Content-Type-Options": "nosniff",
}
#: the page's Content-Security-Policy (``{importmap}``: the hash of its inline import map): scripts from this
#: service only, its sort worker from a blob: URL compiling WebAssembly, requests to this service only, and no
#: framing by another site (a page framed under a decoy could be clicked through unseen)
PAGE_CSP = ("default-src 'self'; script-src 'self' {importmap} 'wasm-unsafe-eval'; worker-src 'self' blob:; "
            "style-src 'self' 'unsafe-inline'; img-src 'self' data: blob:; connect-src 'self'; object-src 'none'; "
            "base-uri 'none'; form-action 'none'; frame-ancestors 'none'")
_MEDIA = {".js": "text/javascript; charset=utf-8", ".css": "text/css; charset=utf-8"}
INSTALL_HINT = ("the web viewer's npm packages are not installed: run `npm ci` in the repository root "
                "(needs Node.js and npm, e.g. `apt-get install nodejs npm`); `bash scripts/serve.sh` does both")


def node_modules_dir() -> Path:
    """Where the viewer's npm packages are: ``$OMNISPLAT_NODE_MODULES`` or ``<repo>/node_modules``."""
    env = os.environ.get("OMNISPLAT_NODE_MODULES")
    return Path(env) if env else REPO_ROOT / "node_modules"


def missing_assets() -> list[str]:
    """npm files the page needs that are not installed (empty when the viewer can be served)."""
    root = node_modules_dir()
    return [rel for rel in NPM_ASSETS.values() if not (root / rel).is_file()]


def _viewer_unavailable() -> ServiceError:
    missing = missing_assets()
    log.warning("web viewer unavailable: missing under %s: %s", node_modules_dir(), ", ".join(missing))
    return ServiceError(f"{INSTALL_HINT} (missing npm files: {', '.join(missing)})",  # no server paths
                        code="viewer_unavailable", status=503)


def script_hash(code: bytes) -> str:
    """The CSP source (``'sha256-...'``) that allows one inline script of exactly ``code`` (this page's import map,
    the docs page's setup script)."""
    return f"'sha256-{base64.b64encode(hashlib.sha256(code).digest()).decode()}'"


def page_csp(template: str) -> str:
    """:data:`PAGE_CSP` for the page ``template``: its inline import map allowed by its SHA-256."""
    found = re.search(r'<script type="importmap">(.*?)</script>', template, re.S)
    return PAGE_CSP.format(importmap="" if found is None else script_hash(found.group(1).encode()))


def _page(scene_id: str, meta: dict, template: str) -> str:
    c2w_a = meta.get("poses", {}).get("c2w", [None])[0]
    config = {
        "scene_id": scene_id,
        "ply": f"/v1/scenes/{scene_id}/gaussians.ply",
        "spz": f"/v1/scenes/{scene_id}/gaussians.spz",  # loaded instead with ?format=spz
        "c2w": [float(v) for row in c2w_a for v in row] if c2w_a else None,  # reference A, OpenCV, row-major
        "fov_deg": DEFAULT_FOV_DEG,  # horizontal, the render API's perspective default
        "num_gaussians": meta.get("num_gaussians"),
    }
    # "</" cannot close the script element from inside the JSON
    blob = json.dumps(config).replace("</", "<\\/")
    return (template.replace("{{CONFIG}}", blob)
            .replace("{{TITLE}}", html.escape(f"omnisplat viewer - scene {scene_id}"))
            .replace("{{PLY}}", html.escape(config["ply"]))
            .replace("{{SPZ}}", html.escape(config["spz"]))
            .replace("{{COUNT}}", html.escape(str(config["num_gaussians"]))))


def _number(name: str, text: str, what: str) -> float:
    """``text`` as a finite number when it is a plain ASCII decimal (as the ``c2w`` query's numbers): the page's
    script reads ``9_0`` or non-ASCII digits as no number, where Python's ``float`` reads 90; else a 422 naming
    ``name``."""
    value = float(text) if PLAIN_DECIMAL.fullmatch(text.strip()) else math.nan
    if not math.isfinite(value):
        raise BadInput(f"{name}: must be {what}, got {text[:40]!r}", code="invalid_render_query")
    return value


def _check_camera(c2w: str | None, fov_deg: str | None, width: str | None, height: str | None) -> None:
    """422 naming the parameter when the page's camera is one the render API refuses: the page would show a
    sheared, mirrored or inside-out view (a field of view past 180 deg turns it over) without a word; or when a
    canvas size is one the page's script cannot read (its error would show on a black page, or not at all
    with ``bare=1``)."""
    if c2w is not None:
        check_camera_reach(parse_c2w_query(c2w))
    if fov_deg is not None:
        check_fov(_number("fov_deg", fov_deg, "a number of degrees"))
    for name, text in (("width", width), ("height", height)):
        if text is not None and not _number(name, text, "a positive number of pixels") > 0:
            raise BadInput(f"{name}: must be a positive number of pixels, got {text[:40]!r}",
                           code="invalid_render_query")


@router.get(
    "/v1/scenes/{scene_id}/viewer", response_class=HTMLResponse, summary="Web 3DGS viewer page for a scene",
    description="An HTML page running GaussianSplats3D (three.js, served by this service from its pinned "
                "npm packages, no CDN) on the scene's `gaussians.ply`, camera at reference A, black "
                "background (the same as the render API's default plain compositing). Orbit with the mouse, "
                "fly with W/A/S/D/Q/E. The query may place the camera: `c2w` (16 or 12 numbers, row-major, "
                "OpenCV), `fov_deg` (horizontal; both checked as the render API checks them: 422 for a non-rigid `c2w` or "
                "a field of view outside 1-170 deg), `width`, `height` (canvas pixels, positive), `bare=1` (no info panel); "
                "`format=spz` loads `gaussians.spz` instead (a fifth of the bytes, for slow links; the browser "
                "takes longer to parse it); any other parameter is a 422. 503 `viewer_unavailable` when the "
                "npm packages are not installed (`npm ci`).",
    responses={200: {"content": {"text/html": {}}, "description": "the viewer page"},
               303: {"description": "with `key`: this URL without it, and a cookie holding the key"},
               **error_responses(400, 404, 422, 503)},
)
async def viewer_page(request: Request, scene_id: SceneId, store: StoreDep, settings: SettingsDep,
                      key: Annotated[str | None, Query(description="the API key, when the service has one: a "
                                                                     "browser cannot send a header, so the answer "
                                                                     "is a 303 to this URL without it that sets a "
                                                                     "same-site cookie")] = None,
                      c2w: Annotated[str | None, Query(description="the page's camera: 16 or 12 comma-separated "
                                                                   "numbers, row-major, OpenCV camera-to-world "
                                                                   "(read by the page; default reference A)")] = None,
                      fov_deg: Annotated[str | None, Query(description="horizontal field of view, degrees "
                                                                       "(read by the page)")] = None,
                      width: Annotated[str | None, Query(description="canvas width, pixels (read by the page)")] = None,
                      height: Annotated[str | None, Query(description="canvas height, pixels (read by the page)")
                                        ] = None,
                      bare: Annotated[str | None, Query(description="`1`: the canvas alone, without the info panel "
                                                                    "(read by the page)")] = None,
                      file: Annotated[Literal["ply", "spz"], Query(
                          alias="format", description="which file the page loads: the PLY (default) or the SPZ, a "
                                                      "fifth of the bytes (read by the page)")] = "ply",
                      ) -> Response:
    _check_camera(c2w, fov_deg, width, height)
    del c2w, fov_deg, width, height, bare, file  # declared so that the query check accepts them; the page's script reads them
    try:
        key = query_key(request.scope).decode("utf-8", "replace") if key is not None else None
    except DuplicateKey as exc:
        raise BadInput(str(exc), code="duplicate_query_parameter", status=400) from None
    if not store.exists(scene_id):
        raise NotFound(f"no scene with id {scene_id!r}", code="scene_not_found")
    if key is not None:  # the guard already checked it: into the cookie, out of the URL
        rest = [(k, v) for k, v in request.query_params.multi_items() if k != "key"]
        target = request.url.path + (f"?{urlencode(rest)}" if rest else "")
        moved = RedirectResponse(target, status_code=303, headers={"Referrer-Policy": "no-referrer",
                                                                   "Cache-Control": "no-store"})
        if settings.api_key:  # percent-encoded: a key's "/", "=" or ";" would be quoted, and then not match
            moved.set_cookie(KEY_COOKIE, quote(key, safe=""), httponly=True, samesite="strict", path="/")
        return moved
    if missing_assets():
        raise _viewer_unavailable()
    meta = await anyio.to_thread.run_sync(store.meta, scene_id)
    template = (PAGE_DIR / "viewer.html").read_text(encoding="utf-8")
    return HTMLResponse(_page(scene_id, meta, template),
                        headers={**ISOLATION_HEADERS, "Content-Security-Policy": page_csp(template),
                                 "X-Frame-Options": "DENY", "Cache-Control": "private, no-cache"})


@router.get("/viewer-assets/{name}", include_in_schema=False)
async def viewer_asset(name: str) -> Response:
    if name in NPM_ASSETS:
        path = node_modules_dir() / NPM_ASSETS[name]
        if not path.is_file():
            raise _viewer_unavailable()
    elif name in PAGE_ASSETS:
        path = PAGE_DIR / PAGE_ASSETS[name]
    else:
        raise NotFound(f"no viewer asset {name!r}", code="not_found")
    return FileResponse(path, media_type=_MEDIA[path.suffix],
                        headers={**ISOLATION_HEADERS, "Cache-Control": "no-cache"})
