"""Service settings: one ``Settings`` class, read from ``OMNISPLAT_*`` environment variables.

Every knob of the service lives here (model, scene store, limits, onnxruntime threads).
CLI flags of ``omnisplat serve`` override the environment; tests build ``Settings(...)``
directly and hand it to :func:`service.app.create_app`.
"""

from __future__ import annotations

import ipaddress
from functools import lru_cache
from pathlib import Path

from pydantic import Field, computed_field, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from .model_files import default_model_name
from .store import DEFAULT_BUDGET_BYTES, DEFAULT_TMP_GRACE_S

DEFAULT_HOME = Path.home() / ".omnisplat"


class Settings(BaseSettings):
    """All service settings; environment variable = ``OMNISPLAT_`` + upper-case field name."""

    model_config = SettingsConfigDict(
        env_prefix="OMNISPLAT_", env_ignore_empty=True, extra="ignore", validate_default=True
    )

    # -- network (used by `omnisplat serve`) --------------------------------
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)
    header_timeout_s: float = Field(10.0, gt=0, description="a connection must send complete request headers "
                                                            "within this many seconds (idle/slow clients closed)")
    body_timeout_s: float = Field(120.0, gt=0, description="a request body must arrive within this many seconds (408)")
    body_min_rate: float = Field(1024.0, ge=0, description="bytes per second a request body must arrive at, "
                                 "measured over each body_rate_window_s while the service waits for it (408 "
                                 "below; a body that ends sooner only needs its remaining bytes); 0 = off")
    body_rate_window_s: float = Field(10.0, gt=0, description="window of the minimum body rate, seconds")
    max_header_bytes: int = Field(64 * 1024, ge=4096, description="request line + headers; more get 431")
    max_requests: int = Field(256, ge=1, description="requests being worked on at once (their body, if any, "
                                                     "received); more get 503 JSON + Retry-After (health and "
                                                     "readiness exempt)")
    max_body_readers: int = Field(64, ge=1, description="requests whose body is still arriving, counted apart "
                                                        "from max_requests so that slow uploads cannot hold the "
                                                        "slots of renders and reads; more get 503 JSON")

    # -- access ---------------------------------------------------------------
    api_key: str | None = Field(None, description="if set, every /v1 request needs 'Authorization: Bearer KEY' "
                                                  "(or X-API-Key); required when host is not a loopback address")
    allow_no_auth: bool = Field(False, description="serve a non-loopback host without api_key (explicit opt-out)")
    allowed_hosts: list[str] | None = Field(None, description="accepted Host header names (DNS-rebinding guard); "
                                                              "unset: loopback names (+ host itself); ['*']: any")
    cors_origins: list[str] = Field(default_factory=list, description="origins allowed to call the API from a "
                                                                      "browser (CORS); empty: none")

    # -- model ----------------------------------------------------------------
    model_path: Path | None = Field(
        None, description="ONNX model file. Unset: <models_dir>/omnisplat-default-<exporter hash>.onnx "
                          "(built by `serve` if missing, rebuilt when the exporter changes)."
    )
    models_dir: Path = DEFAULT_HOME / "models"
    ort_threads: int = Field(2, ge=1, le=256, description="onnxruntime intra-op threads")
    warmup: bool = Field(True, description="build and render one synthetic scene before /readyz turns true")

    # -- scene store ----------------------------------------------------------
    store_dir: Path = DEFAULT_HOME / "scenes"
    store_tmp_grace_s: float = Field(DEFAULT_TMP_GRACE_S, ge=0, description="unfinished writes in the store (tmp/, "
                                     "trash/, artifact .tmp files) younger than this survive a server's start-up: "
                                     "another server sharing the store may be writing them; 0 clears them all "
                                     "(only for a store no other process uses)")
    replica_id: str | None = Field(None, description="names this process in job records (default host:pid)")
    max_scenes: int = Field(0, ge=0, description="scenes kept on disk, least recently used evicted first; 0 = unlimited")
    cache_scenes: int = Field(8, ge=0, description="scenes kept decoded in memory (LRU)")
    cache_bytes: int = Field(1 << 30, ge=0, description="memory bound of the scene cache in bytes")

    # -- input limits ---------------------------------------------------------
    max_upload_bytes: int = Field(100 * 1024 * 1024, ge=1024, description="request body cap (413 beyond)")
    max_image_pixels: int = Field(8192 * 4096, ge=1024, description="decoded pixels per image (decompression bombs)")
    min_image_height: int = Field(32, ge=2, description="smallest ERP height accepted")
    max_render_width: int = Field(4096, ge=8)
    max_render_pixels: int = Field(4096 * 2048, ge=64)
    max_render_cost: float = Field(4096 * 2048 * 1.2e6, gt=0, description="output pixels x (scene Gaussians + "
                                   "150k per pixel for the image's buffers) one render may cost "
                                   "(service.limits.render_cost); 413 beyond")
    heavy_render_cost: float = Field(1024 * 1024 * 1.0e6, gt=0, description="renders above this pixel-Gaussian "
                                     "cost take the reconstruction slot instead of a render slot, so that their "
                                     "memory peak never adds to a reconstruction's")
    min_free_store_bytes: int = Field(256 * 1024 * 1024, ge=0, description="free disk the store must have "
                                      "before a reconstruction or a refinement starts (507 below; /readyz 503)")

    # -- concurrency ----------------------------------------------------------
    inference_concurrency: int = Field(1, ge=1, description="reconstructions running at once")
    inference_queue: int = Field(2, ge=0, description="reconstructions waiting; more get 503")
    render_concurrency: int = Field(1, ge=1, description="renders/PLY encodes running at once")
    render_queue: int = Field(4, ge=0, description="renders waiting; more get 503")
    retry_after_s: int = Field(5, ge=1, description="Retry-After seconds sent with 503")

    # -- scene store budget ----------------------------------------------------
    store_budget_bytes: int = Field(DEFAULT_BUDGET_BYTES, ge=0, description="bytes the stored scenes may take on "
                                    "disk; a write beyond it first evicts the least recently used scenes no job is "
                                    "using (507 when that cannot make room); 0 = no cap. Every write (scene, edit, "
                                    "refinement, selection) also keeps min_free_store_bytes free on the disk")

    @model_validator(mode="after")
    def _check(self) -> "Settings":
        if self.max_render_width * 1 > self.max_render_pixels:
            raise ValueError("max_render_width must not exceed max_render_pixels")
        if self.api_key is not None and (not self.api_key.strip() or self.api_key != self.api_key.strip()):
            # HTTP drops a header value's leading and trailing blanks: no request could send this key
            raise ValueError("api_key (OMNISPLAT_API_KEY) must not be blank nor begin or end with white space "
                             "(a secret file's trailing newline?): no request could send it")
        if self.allowed_hosts is not None and not self.allowed_hosts:
            raise ValueError("allowed_hosts (OMNISPLAT_ALLOWED_HOSTS) is empty: every request, health checks "
                             "included, would be refused; leave it unset for the loopback names, or '[\"*\"]' for any")
        if 2 * self.min_image_height ** 2 > self.max_image_pixels:
            raise ValueError(f"min_image_height {self.min_image_height} needs panoramas of at least "
                             f"{2 * self.min_image_height ** 2} pixels, over max_image_pixels {self.max_image_pixels}: "
                             "every upload would be refused")
        if not self.api_key and not self.allow_no_auth and not is_loopback(self.host):
            raise ValueError(f"host {self.host!r} is not a loopback address: set api_key (OMNISPLAT_API_KEY) "
                             "or allow_no_auth=true to serve without authentication")
        return self

    @property
    def trusted_hosts(self) -> list[str]:
        """Host header names accepted (see ``allowed_hosts``)."""
        if self.allowed_hosts is not None:
            return list(self.allowed_hosts)
        names = ["127.0.0.1", "localhost", "::1", "[::1]"]
        if not is_loopback(self.host) and self.host not in ("0.0.0.0", "::"):
            names.append(self.host)
        return ["*"] if self.host in ("0.0.0.0", "::") else names

    @computed_field  # type: ignore[prop-decorator]
    @property
    def resolved_model_path(self) -> Path:
        """The model file the service loads."""
        return self.model_path if self.model_path is not None else self.models_dir / default_model_name()

    def public(self) -> dict:
        """Settings safe to show at /v1/info: no file paths, no secrets."""
        hidden = {"model_path", "models_dir", "store_dir", "resolved_model_path", "api_key"}
        out = {k: v for k, v in self.model_dump(mode="json").items() if k not in hidden}
        out["auth"] = bool(self.api_key)
        return out


def is_loopback(host: str) -> bool:
    """True for 127.0.0.0/8, ::1 and localhost."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


#: OMNISPLAT_* variables read elsewhere than Settings: the viewer's npm packages, and developer scripts
OTHER_VARIABLES = ("OMNISPLAT_NODE_MODULES", "OMNISPLAT_SCALE_DATA", "OMNISPLAT_WHEEL_DIR", "OMNISPLAT_BENCH_MODELS")


def unknown_variables(environ) -> tuple[list[str], list[str]]:
    """(typos, others) among ``environ``'s ``OMNISPLAT_*`` names that are neither a setting nor in
    :data:`OTHER_VARIABLES`: pydantic-settings ignores them, so a misspelt setting would keep its default without a
    word. ``typos`` say which setting each is close to (``OMNISPLAT_ORT_THREAD``: ``OMNISPLAT_ORT_THREADS``);
    ``others`` are the names close to none (a platform's own variables may share the prefix)."""
    import difflib

    prefix = Settings.model_config["env_prefix"]
    known = [prefix + name.upper() for name in Settings.model_fields]
    typos, others = [], []
    for name in sorted(environ):
        if not name.upper().startswith(prefix) or name.upper() in known or name.upper() in OTHER_VARIABLES:
            continue
        close = difflib.get_close_matches(name.upper(), known, n=1, cutoff=0.8)
        if close:
            typos.append(f"{name} is no setting; did you mean {close[0]}?")
        else:
            others.append(name)
    return typos, others


@lru_cache
def get_settings() -> Settings:
    return Settings()
