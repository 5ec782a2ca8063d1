"""Shared fixtures: where the dev data lives (beside the checkout, CI has it too)."""

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def m3d_dir() -> Path:
    path = SHARED_DATA / "m3d_bedroom"
    if not (path / "scene.json").exists():
        pytest.skip(f"dev data not found at {path}")
    return path


@pytest.fixture(scope="session")
def zind_dir() -> Path:
    path = SHARED_DATA / "zind_room09"
    if not (path / "scene.json").exists():
        pytest.skip(f"dev data not found at {path}")
    return path
