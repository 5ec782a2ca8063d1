"""Asynchronous jobs: ``POST /v1/scenes/{id}/refine`` -> 202 + ``Location: /v1/jobs/{job_id}``,
``GET /v1/jobs/{job_id}`` (conventions section 3).

Reserved for the refinement engineer; the router is already mounted by ``create_app``.
A refined scene is a new scene: store it with
``store.put(content_id("refine", parent_id, params_json, model_sha), gaussians, {..., "parent": parent_id})``
and run the work through a :class:`service.limits.WorkGate` so it is bounded like inference.
"""

from __future__ import annotations

from fastapi import APIRouter

router = APIRouter(tags=["jobs"])
