"""Shared fixtures: where the dev data lives (``../shared/data``, beside the checkout).

A test that needs a dev scene takes it from a fixture here (``m3d_dir``, ``zind_dir``, ``zind2k_dir``), never from
a path of its own. A missing scene SKIPS the test, naming what is missing, so a fresh clone with
nothing beside it runs the rest; with ``CI=true`` (CI has the data) it FAILS instead, so a CI run
cannot pass by skipping.
"""

import os
from pathlib import Path

import pytest

from bench import DEV_DATA


def dev_scene(name: str) -> Path:
    """``../shared/data/<name>``; skip (fail under ``CI=true``) when its scene.json is not there."""
    path = DEV_DATA / name
    if (path / "scene.json").exists():
        return path
    message = (f"dev scene {name!r} not found: {path / 'scene.json'} is missing "
               "(the dev data ../shared/data must lie beside the checkout)")
    if os.environ.get("CI", "").strip().lower() == "true":
        pytest.fail(f"{message}; CI=true, so this is a failure, not a skip")
    pytest.skip(message)


@pytest.fixture(scope="session")
def m3d_dir() -> Path:
    return dev_scene("m3d_bedroom")


@pytest.fixture(scope="session")
def zind_dir() -> Path:
    return dev_scene("zind_room09")


@pytest.fixture(scope="session")
def bedroom_theta_dir() -> Path:
    """Hand-held Ricoh Theta captures of a bedroom, 2048x1024 (a real camera's panoramas)."""
    return dev_scene("bedroom_theta")


@pytest.fixture(scope="session")
def zind2k_dir() -> Path:
    """zind_room09 at its 2048x1024 capture size (the same poses)."""
    return dev_scene("zind_room09_2k")
