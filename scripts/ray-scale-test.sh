#!/usr/bin/env bash
# Scale-out test of `omnisplat serve --ray` on this machine (README "Scale-out on Ray Serve").
# A local Ray cluster: a head node and a second node process (own temp dir), 1 CPU each, one Serve
# proxy on 127.0.0.1:$PORT, the scene store shared by both. Measures scenes POSTed and renders per
# minute with 1 and then 2 replicas (scripts/ray_scale_test.py bench), then with 2 replicas: a scene
# POSTed, rendered and refined through the proxy, job status answered by both replicas, the replica
# running a refinement killed with kill -9 (requests still answered, the job reported failed,
# every stored scene whole). Installs .venv-ray (pip install -e '.[ray,export]'); builds the default
# model if missing. Cleans up with `ray stop --force`; prints PASS or FAIL (exit 0 / 1).
# Env: PORT (8765), GCS_PORT (6390), SECONDS_PER_BENCH (30), CLIENTS (3), OMNISPLAT_SCALE_DATA.
set -uo pipefail
cd "$(dirname "$0")/.."
PORT="${PORT:-8765}"; GCS_PORT="${GCS_PORT:-6390}"
SECS="${SECONDS_PER_BENCH:-30}"; CLIENTS="${CLIENTS:-3}"
URL="http://127.0.0.1:$PORT"
VENV=.venv-ray
if pgrep -x raylet >/dev/null || pgrep -f "gcs_server" >/dev/null; then
    echo "FAIL: a Ray cluster is already running on this machine; 'ray stop --force' here would end it" >&2
    exit 1
fi
python3 -m venv "$VENV" && "$VENV/bin/python" -m pip install -q --disable-pip-version-check -e ".[ray,export]" \
    || { echo "FAIL: could not install .[ray,export]"; exit 1; }
WORK="$(mktemp -d -t omnisplat-ray.XXXXXX)"
export OMNISPLAT_STORE_DIR="$WORK/store" RAY_USAGE_STATS_ENABLED=0 OMP_NUM_THREADS=1
# Token authentication with a token of this run only (a ~/.ray/auth_token left by a local ray.init
# would otherwise switch the head to tokens without the second node knowing).
RAY_AUTH_TOKEN="$(python3 -c 'import secrets; print(secrets.token_hex(32))')"
export RAY_AUTH_MODE=token RAY_AUTH_TOKEN
# The Serve proxy prefers replicas on its own node; off here so that both nodes' replicas take requests.
export RAY_SERVE_PROXY_PREFER_LOCAL_NODE_ROUTING=0
SERVE_PID=""
cleanup() {
    [ -n "$SERVE_PID" ] && kill -TERM "$SERVE_PID" 2>/dev/null && wait "$SERVE_PID" 2>/dev/null
    "$VENV/bin/ray" stop --force >/dev/null 2>&1
    rm -rf "$WORK"
}
trap cleanup EXIT
trap 'exit 143' INT TERM
RAY_NODE=(--node-ip-address=127.0.0.1 --num-cpus=1 --object-store-memory=200000000 --disable-usage-stats)
"$VENV/bin/ray" start --head --port="$GCS_PORT" --include-dashboard=false --temp-dir="$WORK/ray-head" \
    "${RAY_NODE[@]}" >"$WORK/ray-head.log" 2>&1 || { cat "$WORK/ray-head.log"; echo FAIL; exit 1; }
"$VENV/bin/ray" start --address="127.0.0.1:$GCS_PORT" --temp-dir="$WORK/ray-node2" "${RAY_NODE[@]}" \
    >"$WORK/ray-node2.log" 2>&1 || { cat "$WORK/ray-node2.log"; echo FAIL; exit 1; }

serve() {  # serve REPLICAS: (re)deploy with exactly that many replicas and wait for /readyz
    [ -n "$SERVE_PID" ] && { kill -TERM "$SERVE_PID"; wait "$SERVE_PID" 2>/dev/null; }
    "$VENV/bin/omnisplat" serve --ray --ray-address="127.0.0.1:$GCS_PORT" --host 127.0.0.1 --port "$PORT" \
        --min-replicas "$1" --max-replicas "$1" --replica-cpus 1 >>"$WORK/serve.log" 2>&1 &
    SERVE_PID=$!
    "$VENV/bin/python" scripts/ray_scale_test.py "$URL" "$OMNISPLAT_STORE_DIR" wait --replicas "$1" && return 0
    tail -30 "$WORK/serve.log"; return 1
}
export RAY_ADDRESS="127.0.0.1:$GCS_PORT"
status=0
nodes=0
for _ in $(seq 30); do
    nodes="$("$VENV/bin/ray" status 2>/dev/null | grep -c ' node_')"
    [ "$nodes" -ge 2 ] && break
    sleep 2
done
echo "== $nodes Ray nodes (1 CPU each); $(getconf _NPROCESSORS_ONLN) cores, load $(cut -d' ' -f1-3 /proc/loadavg)"
[ "$nodes" -ge 2 ] || { echo "FAIL: the second Ray node did not join"; exit 1; }
for n in 1 2; do
    serve "$n" || { echo "FAIL: $n replica(s) not ready"; exit 1; }
    echo "== $n replica(s), $CLIENTS clients, ${SECS} s each:"
    "$VENV/bin/python" scripts/ray_scale_test.py "$URL" "$OMNISPLAT_STORE_DIR" bench --seconds "$SECS" \
        --clients "$CLIENTS" || status=1
done
echo "== checks with 2 replicas (render, refine, status from both replicas, kill -9 of the job's replica):"
"$VENV/bin/python" scripts/ray_scale_test.py "$URL" "$OMNISPLAT_STORE_DIR" checks || status=1
if [ "$status" = 0 ]; then echo PASS; else tail -40 "$WORK/serve.log"; echo FAIL; fi
exit "$status"
