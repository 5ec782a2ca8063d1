# omnisplat: two ERP panoramas -> 3D Gaussians, served over HTTP on the CPU.
#
#   docker build -t omnisplat .
#   docker run -p 8000:8000 -e OMNISPLAT_API_KEY=change-me -v omnisplat-scenes:/data omnisplat
#   (it binds 0.0.0.0: a key is required unless OMNISPLAT_ALLOW_NO_AUTH=true)
#
# Stage 1 (export) installs torch and builds the ONNX model; the runtime stage copies only
# the .onnx file and installs the runtime dependencies: no torch in the final image.
# On Linux, PyPI's torch wheel pulls CUDA packages; to build faster, pass a CPU-only wheel
# index:  --build-arg PIP_EXTRA_INDEX_URL=<your PyTorch CPU wheel index>
# or a folder holding the CPU wheel (mounted into the build, e.g. `podman build -v DIR:DIR:ro`):
#         --build-arg PIP_FIND_LINKS=DIR
# Without Docker: `bash scripts/container-test.sh` builds and smoke-tests this file with podman.
#
# Only what the service needs goes into the image: rasterizer/, export/ (the export stage;
# the runtime gets export/__init__.py only) and service/. Measurement code (bench/), tests
# and docs stay out. Static web assets, if the service gets them, are copied next to
# service/ in the runtime stage (see the marked line below).

ARG PYTHON_IMAGE=python:3.11-slim

FROM ${PYTHON_IMAGE} AS export
ARG PIP_EXTRA_INDEX_URL=""
ARG PIP_FIND_LINKS=""
ARG MODEL_HEIGHT=512
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_EXTRA_INDEX_URL=${PIP_EXTRA_INDEX_URL} \
    PIP_FIND_LINKS=${PIP_FIND_LINKS}
WORKDIR /src
# Dependencies first, in their own layer: it is rebuilt only when pyproject.toml changes.
COPY pyproject.toml ./
# (the one-liner writes [project].dependencies and the named extras as a requirements file)
RUN python -c 'import sys, tomllib; p = tomllib.load(open("pyproject.toml", "rb"))["project"]; deps = p["dependencies"] + [d for e in sys.argv[1:] for d in p["optional-dependencies"][e]]; open("deps.txt", "w").write(chr(10).join(deps))' export \
    && pip install -r deps.txt && rm deps.txt
COPY README.md ./
COPY rasterizer ./rasterizer
COPY export ./export
COPY service ./service
RUN pip install --no-deps .
RUN python -m service.cli export /models/omnisplat-default.onnx --height ${MODEL_HEIGHT}

# Stage 2 (viewer): the web viewer's pinned npm packages (package-lock.json), built with Debian's
# nodejs/npm; the runtime copies only their build folders (no node in the final image).
FROM ${PYTHON_IMAGE} AS viewer
ENV NODE_EXTRA_CA_CERTS=/etc/ssl/certs/ca-certificates.crt
WORKDIR /src
COPY package.json package-lock.json .npmrc ./
RUN apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends nodejs npm \
    && npm ci --omit=dev --no-audit --no-fund --loglevel=error

FROM ${PYTHON_IMAGE} AS runtime
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 \
    OMP_NUM_THREADS=2 OPENBLAS_NUM_THREADS=2 MKL_NUM_THREADS=2 \
    OMNISPLAT_HOST=0.0.0.0 OMNISPLAT_PORT=8000 \
    OMNISPLAT_MODEL_PATH=/models/omnisplat-default.onnx \
    OMNISPLAT_STORE_DIR=/data/scenes \
    OMNISPLAT_NODE_MODULES=/app/node_modules
WORKDIR /app
# Runtime dependencies only (pyproject [project].dependencies: numpy, onnxruntime, fastapi, scipy, ...),
# in a layer of their own before any source is copied.
COPY pyproject.toml ./
RUN python -c 'import sys, tomllib; p = tomllib.load(open("pyproject.toml", "rb"))["project"]; deps = p["dependencies"] + [d for e in sys.argv[1:] for d in p["optional-dependencies"][e]]; open("deps.txt", "w").write(chr(10).join(deps))' \
    && pip install -r deps.txt && rm deps.txt
COPY --from=viewer /src/node_modules/three/build ./node_modules/three/build
COPY --from=viewer /src/node_modules/@mkkellogg/gaussian-splats-3d/build ./node_modules/@mkkellogg/gaussian-splats-3d/build
COPY --from=viewer /src/node_modules/swagger-ui-dist ./node_modules/swagger-ui-dist
COPY README.md ./
COPY rasterizer ./rasterizer
COPY export/__init__.py ./export/__init__.py
COPY service ./service
# The package itself, without dependencies. The checks: no torch in the image; the app and the
# refine path import with what was installed.
RUN pip install --no-deps . \
    && python -c "import importlib.util, sys; sys.exit(importlib.util.find_spec('torch') is not None)" \
    && python -c "import service.app, service.jobs, rasterizer.refine, scipy.sparse"
COPY --from=export /models/omnisplat-default.onnx /models/omnisplat-default.onnx
RUN useradd --create-home --uid 10001 omnisplat && mkdir -p /data/scenes && chown -R omnisplat /data
USER omnisplat
VOLUME ["/data"]
EXPOSE 8000
HEALTHCHECK --interval=30s --timeout=5s --start-period=60s --retries=3 \
    CMD python -c "import os, urllib.request; urllib.request.urlopen(f'http://127.0.0.1:{os.environ.get(\"OMNISPLAT_PORT\", \"8000\")}/healthz', timeout=4)" || exit 1
# Port and every other setting come from OMNISPLAT_* variables (see service/config.py).
CMD ["omnisplat", "serve", "--no-build"]
