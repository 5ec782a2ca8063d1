"""Helpers shared by tests/service (not a test module): the small model, synthetic panoramas, a live server.

The session fixture ``model_path`` (tests/service/conftest.py) exports the small model once.
"""

from __future__ import annotations

import io
import json
import socket
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import httpx
import numpy as np
from PIL import Image

from rasterizer.geometry import direction_from_lat_lon, erp_lat_lon
from service.config import Settings

IDENTITY = ",".join(str(v) for v in np.eye(4).ravel())


def small_model(tmp_path_factory) -> Path:
    """Export the small test model once per session (a shared path under the session's temp root)."""
    path = tmp_path_factory.getbasetemp() / "omnisplat-test-model" / "small-128x256-p8.onnx"
    if not path.is_file():
        from export.onnx_export import export_model

        export_model(path, height=128, width=256, num_planes=8)
    return path


def panorama(height: int = 128, seed: int = 0, fmt: str = "PNG", shift: int = 0) -> bytes:
    """A textured synthetic ERP (smooth bands + noise), encoded."""
    rng = np.random.default_rng(seed)
    w = 2 * height
    yy, xx = np.mgrid[0:height, 0:w].astype(np.float32)
    xx = (xx + shift) % w
    base = np.stack([np.sin(xx / w * 12.56 + k) * np.cos(yy / height * 6.28 * (k + 1)) for k in range(3)], -1)
    img = 0.5 + 0.35 * base + 0.1 * rng.standard_normal((height, w, 3))
    buf = io.BytesIO()
    Image.fromarray((np.clip(img, 0, 1) * 255).astype(np.uint8)).save(buf, format=fmt)
    return buf.getvalue()


def pose(x: float = 0.0) -> list:
    m = np.eye(4)
    m[0, 3] = x
    return m.tolist()


POSES = json.dumps({"convention": "opencv", "c2w": [pose(0.0), pose(0.5)]})


class LiveServer:
    """uvicorn serving create_app(settings) in a thread, on a free loopback port."""

    def __init__(self, settings: Settings) -> None:
        import uvicorn

        from service.app import create_app
        from service.server import server_config

        self.settings = settings
        self.app = create_app(settings)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind(("127.0.0.1", 0))
        self.url = f"http://127.0.0.1:{self.sock.getsockname()[1]}"
        self.server = uvicorn.Server(server_config(self.app, settings, log_level="warning", timeout_keep_alive=5))
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]}, daemon=True)

    def __enter__(self) -> "LiveServer":
        self.thread.start()
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            try:
                if httpx.get(self.url + "/readyz", timeout=2).status_code == 200:
                    return self
            except httpx.TransportError:
                pass
            if not self.thread.is_alive():
                raise RuntimeError("server thread died during start-up")
            time.sleep(0.05)
        raise TimeoutError("server did not become ready")

    def __exit__(self, *exc) -> None:
        self.server.should_exit = True
        self.thread.join(30)
        self.sock.close()

    def client(self, **kw) -> httpx.Client:
        return httpx.Client(base_url=self.url, timeout=120, **kw)


def make_settings(model: Path, store: Path, **kw) -> Settings:
    return Settings(model_path=model, store_dir=store, **kw)


def post_scene(client: httpx.Client, a: bytes, b: bytes, poses: str = POSES, options: str | None = None,
               names=("a.png", "b.png")) -> httpx.Response:
    data = {"poses": poses}
    if options is not None:
        data["options"] = options
    return client.post("/v1/scenes", files={"image_a": (names[0], a), "image_b": (names[1], b)}, data=data)


def new_scene(client: httpx.Client, seed: int, shift: int) -> str:
    """Id of a scene POSTed from two random panoramas (:func:`panorama` ``seed``, the second shifted by ``shift``)."""
    r = post_scene(client, panorama(seed=seed), panorama(seed=seed, shift=shift))
    assert r.status_code == 201, r.text
    return r.json()["id"]


@contextmanager
def edit_server(model: Path, store: Path):
    """A live server for selection and edit tests (renders up to 512 x 256), ``server.store`` its store folder."""
    with LiveServer(make_settings(model, store, max_render_width=512, max_render_pixels=512 * 256)) as server:
        server.store = store
        yield server


def stored_scene_count(store: Path) -> int:
    scenes = store / "scenes"
    return len([p for p in scenes.iterdir() if (p / "meta.json").exists()]) if scenes.exists() else 0


def ply_with_nan(path: Path, n: int, rows) -> None:
    """A PLY of ``n`` valid Gaussians (tests.rasterizer toy scene) whose x is NaN in ``rows``."""
    from rasterizer.ply import ply_bytes, ply_header, property_names
    from tests.rasterizer._support import toy_scene

    g = toy_scene(3, n=n)
    data = bytearray(ply_bytes(g))
    body = np.frombuffer(data, dtype="<f4", offset=len(ply_header(n, g.sh.shape[1])))
    body.reshape(n, len(property_names(g.sh.shape[1])))[list(rows), 0] = np.nan
    path.write_bytes(bytes(data))


def render_argv(tmp_path: Path, ply: str) -> list[str]:
    """``omnisplat render`` arguments: ``tmp_path / ply`` at the identity pose, 64 px wide, to ``view.png``."""
    return ["render", str(tmp_path / ply), "--c2w", IDENTITY, "--width", "64", "-o", str(tmp_path / "view.png")]


ROOM_MIN = np.array([-3.0, -1.2, -3.5])  # camera A at the origin, OpenCV (y down): floor at y = 1.5
ROOM_MAX = np.array([3.5, 1.5, 4.0])
_LATTICE = np.random.default_rng(7).random((64, 64, 64, 3)).astype(np.float32)


def _noise(p: np.ndarray, cell: float) -> np.ndarray:
    """Trilinear value noise on a random lattice with ``cell`` metres spacing, (..., 3) in [0, 1]."""
    q = p / cell
    i = np.floor(q).astype(int)
    f = q - i
    f = f * f * (3 - 2 * f)
    out = 0.0
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                w = (f[..., 0] if dx else 1 - f[..., 0]) * (f[..., 1] if dy else 1 - f[..., 1]) * \
                    (f[..., 2] if dz else 1 - f[..., 2])
                out = out + w[..., None] * _LATTICE[(i[..., 0] + dx) % 64, (i[..., 1] + dy) % 64, (i[..., 2] + dz) % 64]
    return out


def room_erp(c2w: np.ndarray, height: int = 384, supersample: int = 1) -> np.ndarray:
    """uint8 ERP (H, 2H, 3) of the textured box room seen from ``c2w`` (ray-cast, OpenCV frames): each face
    shaded differently and the walls in 0.7-m panels, so that the room has vertical edges as real rooms do.
    ``supersample``: rays per pixel side, box-filtered (smooth edges, as a camera's optics give)."""
    lat, lon = erp_lat_lon(height * supersample, 2 * height * supersample)
    d = direction_from_lat_lon(lat, lon) @ c2w[:3, :3].T
    o = c2w[:3, 3]
    with np.errstate(divide="ignore"):
        tt = np.where(d > 0, (ROOM_MAX - o) / d, (ROOM_MIN - o) / d)
    p = o + np.min(tt, axis=-1, keepdims=True) * d
    face = np.argmin(tt, axis=-1) * 2 + (np.take_along_axis(d, np.argmin(tt, axis=-1)[..., None], -1)[..., 0] > 0)
    panel = np.where(face // 2 == 0, np.floor(p[..., 2] / 0.7), np.floor(p[..., 0] / 0.7)) % 2
    shade = np.array([0.8, 1.0, 0.7, 0.9, 0.75, 0.95])[face] * np.where(face // 2 == 1, 1.0, 0.6 + 0.4 * panel)
    tex = (0.55 * _noise(p, 0.08) + 0.45 * _noise(p, 0.3)) * shade[..., None]
    tex = tex.reshape(height, supersample, 2 * height, supersample, 3).mean((1, 3))
    return (np.clip(tex, 0, 1) * 255).astype(np.uint8)


def random_gaussians(n: int, seed: int = 0):
    """``n`` Gaussians of random positions, sizes 0.01-0.1, rotations, opacities and colours (store tests)."""
    from rasterizer.gaussians import Gaussians

    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    return Gaussians(rng.normal(size=(n, 3)), rng.uniform(0.01, 0.1, (n, 3)), q / np.linalg.norm(q, axis=1, keepdims=True),
                     rng.uniform(0, 1, n), rng.normal(size=(n, 1, 3)))


def same_gaussians(a, b) -> bool:
    """Whether two Gaussians' five fields are equal to the bit."""
    return all(np.array_equal(getattr(a, f), getattr(b, f)) for f in ("means", "scales", "quats", "opacities", "sh"))
