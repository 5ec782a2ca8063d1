"""Helpers shared by tests/service: the live-server fixtures of the service API tests."""

from __future__ import annotations

try:  # tests are being reorganised into tests/service/; accept either location
    from tests.service.test_service_api import (IDENTITY, LiveServer, make_settings, panorama,  # noqa: F401
                                                post_scene, small_model)
except ImportError:
    from tests.test_service_api import (IDENTITY, LiveServer, make_settings, panorama, post_scene,  # noqa: F401
                                        small_model)
