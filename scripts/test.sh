#!/usr/bin/env bash
# Install everything the tests need into .venv (fresh machine safe) and run them.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m venv .venv
.venv/bin/python -m pip install -q --disable-pip-version-check -e ".[export,test,bench]"
.venv/bin/python -m ruff check .
source scripts/viewer_deps.sh
install_chromium      # the viewer's browser test (tests/service/test_viewer.py) runs Debian's chromium
install_viewer        # npm ci: the viewer's packages and puppeteer-core
exec .venv/bin/python -m pytest "$@"
