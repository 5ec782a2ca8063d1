#!/usr/bin/env bash
# Install omnisplat into .venv, build the default ONNX model if missing, and serve it.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m venv .venv
.venv/bin/python -m pip install -q --disable-pip-version-check -e ".[export]"
exec .venv/bin/omnisplat serve "$@"
