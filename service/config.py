"""Service settings: one ``Settings`` class, read from ``OMNISPLAT_*`` environment variables.

Every knob of the service lives here (model, scene store, limits, onnxruntime threads).
CLI flags of ``omnisplat serve`` override the environment; tests build ``Settings(...)``
directly and hand it to :func:`service.app.create_app`.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from pydantic import Field, computed_field, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from .model_files import default_model_name

DEFAULT_HOME = Path.home() / ".omnisplat"


class Settings(BaseSettings):
    """All service settings; environment variable = ``OMNISPLAT_`` + upper-case field name."""

    model_config = SettingsConfigDict(
        env_prefix="OMNISPLAT_", env_ignore_empty=True, extra="ignore", validate_default=True
    )

    # -- network (used by `omnisplat serve`) --------------------------------
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)

    # -- model ----------------------------------------------------------------
    model_path: Path | None = Field(
        None, description="ONNX model file. Unset: <models_dir>/omnisplat-default-<exporter hash>.onnx "
                          "(built by `serve` if missing, rebuilt when the exporter changes)."
    )
    models_dir: Path = DEFAULT_HOME / "models"
    ort_threads: int = Field(2, ge=1, le=256, description="onnxruntime intra-op threads")
    warmup: bool = Field(True, description="run one inference before /readyz turns true")

    # -- scene store ----------------------------------------------------------
    store_dir: Path = DEFAULT_HOME / "scenes"
    store_tmp_grace_s: float = Field(0.0, ge=0, description="unfinished writes in the store's tmp/ younger than "
                                                            "this survive start-up (other replicas sharing the "
                                                            "store may be writing them)")
    replica_id: str | None = Field(None, description="names this process in job records (default host:pid)")
    max_scenes: int = Field(0, ge=0, description="scenes kept on disk, oldest evicted first; 0 = unlimited")
    cache_scenes: int = Field(8, ge=0, description="scenes kept decoded in memory (LRU)")
    cache_bytes: int = Field(1 << 30, ge=0, description="memory bound of the scene cache in bytes")

    # -- input limits ---------------------------------------------------------
    max_upload_bytes: int = Field(100 * 1024 * 1024, ge=1024, description="request body cap (413 beyond)")
    max_image_pixels: int = Field(8192 * 4096, ge=1024, description="decoded pixels per image (decompression bombs)")
    min_image_height: int = Field(32, ge=2, description="smallest ERP height accepted")
    max_render_width: int = Field(4096, ge=8)
    max_render_pixels: int = Field(4096 * 2048, ge=64)

    # -- concurrency ----------------------------------------------------------
    inference_concurrency: int = Field(1, ge=1, description="reconstructions running at once")
    inference_queue: int = Field(2, ge=0, description="reconstructions waiting; more get 503")
    render_concurrency: int = Field(1, ge=1, description="renders/PLY encodes running at once")
    render_queue: int = Field(4, ge=0, description="renders waiting; more get 503")
    retry_after_s: int = Field(5, ge=1, description="Retry-After seconds sent with 503")

    @model_validator(mode="after")
    def _check(self) -> "Settings":
        if self.max_render_width * 1 > self.max_render_pixels:
            raise ValueError("max_render_width must not exceed max_render_pixels")
        return self

    @computed_field  # type: ignore[prop-decorator]
    @property
    def resolved_model_path(self) -> Path:
        """The model file the service loads."""
        return self.model_path if self.model_path is not None else self.models_dir / default_model_name()

    def public(self) -> dict:
        """Settings safe to show at /v1/info (paths as strings)."""
        return self.model_dump(mode="json")


@lru_cache
def get_settings() -> Settings:
    return Settings()
