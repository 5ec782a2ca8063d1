#!/usr/bin/env bash
# Build the project's Dockerfile with podman (no Docker engine, no container registry needed)
# and smoke-test the image: /readyz, a reconstruction from the shipped sample (samples/room), a render,
# the PLY, a refine job polled to `done`, the viewer page (when the service has that route),
# the non-root user, the writable /data volume and the HEALTHCHECK command.
#
#   sudo bash scripts/container-test.sh        # run as root; ~2 min (~1 min with the base image cached)
#
# Prints `PASS ...` (image size, build time, smoke timings) and exits 0, or `FAIL: ...` and exits 1.
# It installs podman/buildah/runc/debootstrap with apt when missing. Nothing under /etc is changed:
# podman reads this script's own containers.conf (CONTAINERS_CONF).
#
# The base image (Debian bookworm + python3 in a venv at /opt/venv) is made locally with
# debootstrap from the apt mirror this machine already uses, imported as $BASE_IMAGE and kept
# as a cache. Everything else it makes (image, container, volume, temp dir) is removed on exit.
#
# Environment:
#   BASE_IMAGE           base image tag (default localhost/pybase:bookworm)
#   REBUILD_BASE=1       rebuild the base image even when it exists
#   KEEP_BASE=0          remove the base image at the end too
#   OMNISPLAT_WHEEL_DIR  folder with the CPU torch wheel (default: searched for; see find_wheel_dir)
set -euo pipefail

ROOT=$(cd "$(dirname "$0")/.." && pwd)
BASE_IMAGE=${BASE_IMAGE:-localhost/pybase:bookworm}
KEEP_BASE=${KEEP_BASE:-1}
RUN_ID="omnisplat-ct-$$-$RANDOM"
IMAGE="localhost/$RUN_ID:latest"
CTR="$RUN_ID"
VOL="$RUN_ID-data"
WORK=""
PASSED=0
FAILED=0
MADE_IMAGE=0
MADE_CTR=0
MADE_VOL=0

log() { printf '[container-test %s] %s\n' "$(date +%T)" "$*" >&2; }
fail() {
    log "FAIL: $*"
    if [ "$MADE_CTR" = 1 ]; then
        log "last container log lines:"
        podman logs --tail 40 "$CTR" >&2 2>&1 || true
    fi
    echo "FAIL: $*"
    FAILED=1
    exit 1
}
now() { date +%s.%N; }
since() { python3 -c "import sys; print(f'{float(sys.argv[2]) - float(sys.argv[1]):.1f}')" "$1" "$(now)"; }

cleanup() {
    local rc=$?
    set +e
    if [ "$FAILED" != 1 ] && [ "$rc" != 0 ] && [ "$MADE_CTR" = 1 ]; then
        podman logs --tail 40 "$CTR" >&2 2>&1
    fi
    [ "$MADE_CTR" = 1 ] && podman rm -f -t 2 "$CTR" >/dev/null 2>&1
    [ "$MADE_VOL" = 1 ] && podman volume rm -f "$VOL" >/dev/null 2>&1
    [ "$MADE_IMAGE" = 1 ] && podman rmi -f "$IMAGE" >/dev/null 2>&1
    # intermediate (export-stage) images of this build carry its label
    if [ -n "${CONTAINERS_CONF:-}" ]; then
        podman images -a -q --filter "label=omnisplat.container-test=$RUN_ID" 2>/dev/null \
            | sort -u | xargs -r podman rmi -f >/dev/null 2>&1
    fi
    if [ "$KEEP_BASE" = 0 ]; then podman rmi -f "$BASE_IMAGE" >/dev/null 2>&1; fi
    [ -n "$WORK" ] && rm -rf "$WORK"
    if [ "$FAILED" != 1 ] && [ "$rc" != 0 ]; then
        # an unexpected error under `set -e` (fail() has already said why otherwise)
        echo "FAIL: container test exited with status $rc"
    fi
    exit "$rc"
}
trap cleanup EXIT
trap 'exit 130' INT TERM

# --- prerequisites -------------------------------------------------------------------------
[ "$(id -u)" = 0 ] || fail "run as root (podman builds and runs rootful here): sudo bash scripts/container-test.sh"
SCENE="$ROOT/samples/room"  # the sample that ships with the repo: no dev data needed
[ -f "$SCENE/scene.json" ] && [ -f "$SCENE/images/00.png" ] && [ -f "$SCENE/images/02.png" ] \
    || fail "the sample scene is missing: expected $SCENE/{scene.json,images/00.png,images/02.png}"
command -v python3 >/dev/null || fail "python3 is needed on the host (JSON handling)"
command -v curl >/dev/null || NEED_PKGS="curl"

missing=()
for tool in podman buildah runc debootstrap ${NEED_PKGS:-}; do
    command -v "$tool" >/dev/null || missing+=("$tool")
done
if [ "${#missing[@]}" -gt 0 ]; then
    log "installing ${missing[*]} with apt"
    export DEBIAN_FRONTEND=noninteractive
    apt-get install -y -q podman buildah runc debootstrap curl >/dev/null 2>&1 \
        || { apt-get update -q >/dev/null && apt-get install -y -q podman buildah runc debootstrap curl >/dev/null; } \
        || fail "apt-get install podman buildah runc debootstrap failed"
fi

WORK=$(mktemp -d -t omnisplat-ct.XXXXXX)
# crun cannot set rlimits / handle the hybrid cgroup layout here: runc, explicit ulimits.
cat >"$WORK/containers.conf" <<'EOF'
[containers]
default_ulimits = ["nofile=20000:20000", "nproc=32768:32768"]

[engine]
runtime = "runc"
EOF
export CONTAINERS_CONF="$WORK/containers.conf"

# --- base image: Debian bookworm + python3 venv, made with debootstrap -----------------------
apt_mirror() {
    # the first non-security Debian URI of the apt sources this machine uses (deb822 or one-line)
    local f uri
    for f in /etc/apt/sources.list.d/*.sources; do
        [ -f "$f" ] || continue
        uri=$(awk 'tolower($1)=="uris:" {for (i = 2; i <= NF; i++) print $i}' "$f" | grep -v security | head -n1)
        [ -n "$uri" ] && { echo "$uri"; return; }
    done
    for f in /etc/apt/sources.list /etc/apt/sources.list.d/*.list; do
        [ -f "$f" ] || continue
        uri=$(awk '$1=="deb" {for (i = 2; i <= NF; i++) if ($i ~ /^[a-z]+:\/\//) {print $i; break}}' "$f" \
              | grep -v security | head -n1)
        [ -n "$uri" ] && { echo "$uri"; return; }
    done
}

BASE_SECONDS="cached"
if [ "${REBUILD_BASE:-0}" = 1 ] || ! podman image exists "$BASE_IMAGE"; then
    t0=$(now)
    MIRROR=$(apt_mirror)
    [ -n "$MIRROR" ] || fail "no Debian mirror found in /etc/apt/sources.list{,.d/*}"
    log "making base image $BASE_IMAGE with debootstrap (mirror from apt sources: $MIRROR)"
    rootfs="$WORK/rootfs"
    debootstrap --variant=minbase --include=python3,python3-venv,python3-pip,ca-certificates,passwd \
        bookworm "$rootfs" "$MIRROR" >"$WORK/debootstrap.log" 2>&1 \
        || { tail -n 20 "$WORK/debootstrap.log" >&2; fail "debootstrap failed"; }
    chroot "$rootfs" /usr/bin/python3 -m venv /opt/venv || fail "python3 -m venv in the base rootfs failed"
    rm -rf "$rootfs"/var/cache/apt/archives/*.deb "$rootfs"/var/lib/apt/lists/* "$rootfs/tmp"/*
    tar -C "$rootfs" --numeric-owner -cf - . | podman import \
        --change 'ENV PATH=/opt/venv/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
        --change 'ENV LANG=C.UTF-8' \
        --change 'CMD ["python"]' \
        - "$BASE_IMAGE" >"$WORK/import.log" 2>&1 \
        || { tail -n 20 "$WORK/import.log" >&2; fail "podman import of the base rootfs failed"; }
    rm -rf "$rootfs"
    BASE_SECONDS="built in $(since "$t0") s"
    log "base image $BASE_SECONDS"
else
    log "base image $BASE_IMAGE exists (cached)"
fi

# --- build ---------------------------------------------------------------------------------
find_wheel_dir() {
    # a folder holding the CPU torch wheel pinned in pyproject (PyPI's own torch wheel is the CUDA build)
    local ver pat d
    ver=$(grep -o 'torch==[0-9.]*' "$ROOT/pyproject.toml" | head -n1 | cut -d= -f3)
    [ -n "$ver" ] || return 0
    pat="torch-${ver}+cpu-cp311-*.whl"
    for d in ${OMNISPLAT_WHEEL_DIR:-} ${PIP_FIND_LINKS:-} \
             $(python3 -m pip config get global.find-links 2>/dev/null || true) /opt/wheels; do
        d=${d#file://}
        if [ -d "$d" ] && compgen -G "$d/$pat" >/dev/null; then echo "$d"; return; fi
    done
    d=$(find / -xdev -name "$pat" -print -quit 2>/dev/null || true)
    [ -n "$d" ] && dirname "$d"
}

build_args=(--build-arg "PYTHON_IMAGE=$BASE_IMAGE")
mounts=()
[ -f /etc/ssl/certs/ca-certificates.crt ] \
    && mounts+=(-v /etc/ssl/certs/ca-certificates.crt:/etc/ssl/certs/ca-certificates.crt:ro)
WHEEL_DIR=$(find_wheel_dir || true)
if [ -n "$WHEEL_DIR" ]; then
    log "CPU torch wheel from $WHEEL_DIR"
    mounts+=(-v "$WHEEL_DIR:/wheels:ro")
    build_args+=(--build-arg PIP_FIND_LINKS=/wheels)
else
    log "no local CPU torch wheel found: the export stage downloads torch from PyPI (CUDA build, slow)"
fi

log "building $IMAGE from $ROOT/Dockerfile"
t0=$(now)
MADE_IMAGE=1
podman build --format docker --network host --layers=false \
    --label "omnisplat.container-test=$RUN_ID" \
    "${build_args[@]}" "${mounts[@]}" -t "$IMAGE" -f "$ROOT/Dockerfile" "$ROOT" >"$WORK/build.log" 2>&1 \
    || { tail -n 40 "$WORK/build.log" >&2; fail "podman build failed (log tail above)"; }
BUILD_SECONDS=$(since "$t0")
SIZE_MB=$(podman image inspect --format '{{.Size}}' "$IMAGE" | python3 -c "import sys; print(f'{int(sys.stdin.read()) / 1e6:.0f}')")
log "built in ${BUILD_SECONDS} s, image ${SIZE_MB} MB"

# --- run -----------------------------------------------------------------------------------
PORT=$(python3 -c "import socket; s = socket.socket(); s.bind(('127.0.0.1', 0)); print(s.getsockname()[1])")
URL="http://127.0.0.1:$PORT"
# The image binds 0.0.0.0, so the service requires an API key (or an explicit OMNISPLAT_ALLOW_NO_AUTH):
# start it with one and send it with every request below.
API_KEY=$(python3 -c "import secrets; print(secrets.token_hex(16))")
curl() { command curl -H "Authorization: Bearer $API_KEY" "$@"; }
podman volume create "$VOL" >/dev/null && MADE_VOL=1
t0=$(now)
MADE_CTR=1
# (podman logs that it cannot reach systemd to schedule the HEALTHCHECK: expected, see below)
podman run -d --name "$CTR" -e OMNISPLAT_API_KEY="$API_KEY" -p "127.0.0.1:$PORT:8000" -v "$VOL:/data" "$IMAGE" >/dev/null 2>"$WORK/run.log" \
    || { cat "$WORK/run.log" >&2; fail "podman run failed"; }

ready=0
for _ in $(seq 1 240); do
    code=$(curl -s -o /dev/null -w '%{http_code}' "$URL/readyz" || true)
    [ "$code" = 200 ] && { ready=1; break; }
    [ "$(podman inspect --format '{{.State.Running}}' "$CTR")" = true ] || fail "container exited before /readyz"
    sleep 0.5
done
[ "$ready" = 1 ] || fail "/readyz did not answer 200 within 120 s (last: $code)"
T_READY=$(since "$t0")
log "/readyz 200 after $T_READY s"

# who runs the service, and can it write the volume?
uid=$(podman exec "$CTR" id -u)
[ "$uid" != 0 ] || fail "the service runs as root"
[ "$uid" = 10001 ] || fail "unexpected uid $uid (the Dockerfile creates uid 10001)"
podman exec "$CTR" sh -c 'f=/data/.write-test-$$ && echo ok >"$f" && rm "$f"' \
    || fail "/data is not writable by uid $uid"

# only the service goes into the image (no bench/, tests/, docs/)
for d in bench tests docs; do
    podman exec "$CTR" test ! -e "/app/$d" || fail "/app/$d is in the image"
done
code=$(command curl -s -o /dev/null -w '%{http_code}' "$URL/v1/info")
[ "$code" = 401 ] || fail "GET /v1/info without the API key answered $code, expected 401"
MODEL_SHA=$(curl -sf "$URL/v1/info" | python3 -c "import json, sys; print(json.load(sys.stdin)['model'].get('sha256', '?'))") \
    || fail "GET /v1/info failed"
log "model sha256 $MODEL_SHA"

# POST the sample's pair 00 + 02 with the poses from scene.json
POSES=$(python3 - "$SCENE/scene.json" <<'EOF'
import json, sys
scene = json.load(open(sys.argv[1]))
frames = {f["name"]: f["c2w"] for f in scene["frames"]}
print(json.dumps({"convention": scene.get("convention", "opencv"), "c2w": [frames["00"], frames["02"]]}))
EOF
)
jget() { python3 -c "import json, sys; d = json.load(open(sys.argv[1])); print(eval(sys.argv[2], {}, {'d': d}))" "$@"; }

t0=$(now)
code=$(curl -s -o "$WORK/created.json" -w '%{http_code}' -X POST "$URL/v1/scenes" \
    -F "image_a=@$SCENE/images/00.png;type=image/png" -F "image_b=@$SCENE/images/02.png;type=image/png" \
    -F "poses=$POSES")
[ "$code" = 201 ] || fail "POST /v1/scenes answered $code: $(head -c 500 "$WORK/created.json")"
T_CREATE=$(since "$t0")
SCENE_ID=$(jget "$WORK/created.json" 'd["id"]')
NG=$(jget "$WORK/created.json" 'd["num_gaussians"]')
[ "$NG" -gt 0 ] || fail "scene has $NG Gaussians"
log "POST /v1/scenes 201 in $T_CREATE s: $SCENE_ID, $NG Gaussians"
podman exec "$CTR" sh -c "ls /data/scenes | grep -q ." || fail "nothing was stored under /data/scenes"

# a render at view 01, between the two references
C2W=$(python3 -c "import json, sys; f = {f['name']: f['c2w'] for f in json.load(open(sys.argv[1]))['frames']}; print(','.join(repr(float(v)) for r in f['01'] for v in r))" "$SCENE/scene.json")
t0=$(now)
code=$(curl -s -o "$WORK/render.png" -D "$WORK/render.h" -w '%{http_code}' \
    "$URL/v1/scenes/$SCENE_ID/render?c2w=$C2W&width=512")
[ "$code" = 200 ] || fail "render answered $code: $(head -c 500 "$WORK/render.png")"
T_RENDER=$(since "$t0")
[ "$(head -c 8 "$WORK/render.png" | od -An -tx1 | tr -d ' \n')" = 89504e470d0a1a0a ] \
    || fail "render is not a PNG"
log "render 200 (PNG, $(stat -c %s "$WORK/render.png") bytes) in $T_RENDER s"

# the PLY
t0=$(now)
code=$(curl -s -o "$WORK/scene.ply" -w '%{http_code}' "$URL/v1/scenes/$SCENE_ID/gaussians.ply")
[ "$code" = 200 ] || fail "gaussians.ply answered $code"
T_PLY=$(since "$t0")
head -c 200 "$WORK/scene.ply" | grep -aq "element vertex $NG" \
    || fail "the PLY header does not announce $NG vertices"
log "gaussians.ply 200 ($(stat -c %s "$WORK/scene.ply") bytes) in $T_PLY s"

# a refine job, polled to done
t0=$(now)
code=$(curl -s -o "$WORK/job.json" -w '%{http_code}' -X POST -H 'Content-Type: application/json' \
    -d '{}' "$URL/v1/scenes/$SCENE_ID/refine")
[ "$code" = 202 ] || fail "POST refine answered $code: $(head -c 500 "$WORK/job.json")"
JOB_ID=$(jget "$WORK/job.json" 'd["id"]')
status=queued
for _ in $(seq 1 600); do
    curl -sf -o "$WORK/job.json" "$URL/v1/jobs/$JOB_ID" || fail "GET /v1/jobs/$JOB_ID failed"
    status=$(jget "$WORK/job.json" 'd["status"]')
    case "$status" in done|failed) break ;; esac
    sleep 0.5
done
[ "$status" = done ] || fail "refine job ended '$status': $(jget "$WORK/job.json" 'd.get("error")')"
T_REFINE=$(since "$t0")
REFINED=$(jget "$WORK/job.json" 'd["scene_id"]')
code=$(curl -s -o /dev/null -w '%{http_code}' "$URL/v1/scenes/$REFINED")
[ "$code" = 200 ] || fail "refined scene $REFINED answered $code"
log "refine job done in $T_REFINE s -> scene $REFINED"

# the viewer page, when this version of the service has it
curl -sf -o "$WORK/openapi.json" "$URL/openapi.json" || fail "GET /openapi.json failed"
VIEWER=skipped
if grep -rqsi viewer "$ROOT/service/routes" \
    || python3 -c "import json, sys; sys.exit(not any('viewer' in p for p in json.load(open(sys.argv[1]))['paths']))" \
        "$WORK/openapi.json"; then
    code=$(curl -s -o "$WORK/viewer.html" -D "$WORK/viewer.h" -w '%{http_code}' "$URL/v1/scenes/$SCENE_ID/viewer")
    [ "$code" = 200 ] || fail "GET /v1/scenes/$SCENE_ID/viewer answered $code"
    grep -iq '^content-type: *text/html' "$WORK/viewer.h" \
        || fail "the viewer page is not text/html: $(grep -i '^content-type' "$WORK/viewer.h")"
    VIEWER="200 text/html"
    log "viewer page $VIEWER"
fi

# the image's HEALTHCHECK command (podman schedules it through systemd; run it by hand)
[ "$(podman inspect --format '{{if .Config.Healthcheck}}yes{{end}}' "$CTR")" = yes ] \
    || fail "the image has no HEALTHCHECK (built with --format docker?)"
podman healthcheck run "$CTR" >/dev/null || fail "podman healthcheck run: unhealthy"
log "healthcheck healthy"

PASSED=1
echo "PASS: image $SIZE_MB MB, build ${BUILD_SECONDS} s (base image $BASE_SECONDS); readyz ${T_READY} s," \
     "create ${T_CREATE} s ($NG Gaussians), render ${T_RENDER} s, ply ${T_PLY} s, refine job ${T_REFINE} s," \
     "viewer $VIEWER, uid $uid, /data writable, healthcheck healthy"
