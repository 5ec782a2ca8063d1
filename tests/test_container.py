"""The image works: build the Dockerfile with podman and smoke-test it (scripts/container-test.sh).

Runs in CI through ``scripts/test.sh`` (about 2 min; 1 min with the cached base image). It does
not skip when podman is missing -- the script installs it. It needs root (rootful podman);
without root it fails and says so. Leave it out locally with ``-m "not container"``.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.container
def test_image_builds_and_serves():
    proc = subprocess.run(["bash", str(ROOT / "scripts" / "container-test.sh")], cwd=ROOT,
                          capture_output=True, text=True, timeout=1800)
    out = proc.stdout.strip().splitlines()
    last = out[-1] if out else ""
    detail = f"exit {proc.returncode}\n--- stdout\n{proc.stdout[-4000:]}\n--- stderr\n{proc.stderr[-8000:]}"
    assert proc.returncode == 0, detail
    assert last.startswith("PASS"), detail
    print(last)
