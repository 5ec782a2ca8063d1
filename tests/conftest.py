"""Shared fixtures: where the dev data lives (beside the checkout, CI has it too).

A missing dev scene is a failure, not a skip: the tests that need it cannot pass
without it, and CI always has ``../shared/data``.
"""

from pathlib import Path

import pytest

from bench import DEV_DATA


def _scene(name: str) -> Path:
    path = DEV_DATA / name
    if not (path / "scene.json").exists():
        pytest.fail(f"dev scene {name!r} not found at {path}: the checkout needs ../shared/data beside it")
    return path


@pytest.fixture(scope="session")
def m3d_dir() -> Path:
    return _scene("m3d_bedroom")


@pytest.fixture(scope="session")
def zind_dir() -> Path:
    return _scene("zind_room09")
