"""Response schemas of the HTTP API (documented in the OpenAPI at /docs)."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field


class ErrorDetail(BaseModel):
    code: str = Field(examples=["bad_aspect_ratio"])
    message: str


class ErrorResponse(BaseModel):
    error: ErrorDetail


class Links(BaseModel):
    """Where to go from a scene. The object links are null when the scene keeps no correspondences (a
    refinement that changed the Gaussians' count), ``parent`` is null for a reconstruction."""

    self: str
    render: str
    ply: str
    spz: str
    viewer: str = Field(description="a web 3DGS viewer page of the scene")
    selections: str | None = Field(description="POST a selection of an object here")
    segments: str | None = Field(description="GET the automatic segments (PNG)")
    edits: str | None = Field(description="POST an edit of a selection here (the result is a new scene)")
    parent: str | None = Field(description="the scene this one was made from by an edit or a refinement")


class SceneCreated(BaseModel):
    id: str = Field(description="content hash of inputs, options and model: same inputs, same id")
    num_gaussians: int
    timings: dict[str, float] = Field(description="seconds per stage of this request")
    links: Links
    cached: bool = Field(False, description="true when the scene already existed and nothing was recomputed")


class SceneMeta(BaseModel):
    """Stored metadata of a scene (more keys may appear; unknown ones are passed through)."""

    model_config = ConfigDict(extra="allow")

    id: str
    num_gaussians: int
    created_at: float
    model: dict[str, Any]
    poses: dict[str, Any]
    options: dict[str, Any]
    timings: dict[str, float]
    parent: str | None = None
    links: Links


class Health(BaseModel):
    status: str


class Ready(BaseModel):
    ready: bool
    error: str | None = None


class Info(BaseModel):
    service: str
    service_version: str
    model: dict[str, Any]
    ready: bool
    settings: dict[str, Any]


def error_responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    """``responses=`` entries declaring the JSON error body for the given statuses."""
    text = {400: "Malformed input", 404: "Unknown scene", 408: "Request body too slow", 413: "Upload, image or render "
            "too large", 422: "Invalid input", 503: "Busy or not ready (see Retry-After)",
            507: "The scene store cannot take writes (disk full or read-only)"}
    return {c: {"model": ErrorResponse, "description": text.get(c, "Error")} for c in codes}
