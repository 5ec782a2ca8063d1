"""Helpers shared by tests/service: the live-server fixtures of the service API tests."""

from __future__ import annotations

from tests.service.test_service_api import IDENTITY, LiveServer, make_settings, panorama, post_scene, small_model  # noqa: F401
