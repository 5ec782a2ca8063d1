#!/usr/bin/env bash
# Install omnisplat into .venv and the web viewer's npm packages (npm ci; Node.js via apt-get if
# missing), build the default ONNX model if missing, and serve it.
# Extra arguments go to `omnisplat serve` (e.g. --port 9000); settings also come from
# OMNISPLAT_* variables. Model in ./models, scenes in ./.omnisplat/scenes unless set.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m venv .venv
.venv/bin/python -m pip install -q --disable-pip-version-check -e ".[export]"
source scripts/viewer_deps.sh
if ! install_viewer; then  # the API works without it; /v1/scenes/{id}/viewer then answers 503
    echo "warning: the web viewer could not be installed (npm ci); its page will answer 503" >&2
fi
export OMNISPLAT_MODELS_DIR="${OMNISPLAT_MODELS_DIR:-$PWD/models}"
export OMNISPLAT_STORE_DIR="${OMNISPLAT_STORE_DIR:-$PWD/.omnisplat/scenes}"
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-2}"
exec .venv/bin/omnisplat serve "$@"
