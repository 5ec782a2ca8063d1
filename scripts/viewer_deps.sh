# Sourced by scripts/serve.sh and scripts/test.sh (from the repository root): installs the web viewer's
# and the API docs' pinned npm packages (package.json / package-lock.json -> node_modules, served by the
# service at /v1/scenes/{id}/viewer and /docs, no CDN) and, for the tests, Debian's chromium. Uses apt-get (as root, or
# through sudo) for what is missing.

_as_root() {
    if [ "$(id -u)" -eq 0 ]; then "$@"
    elif command -v sudo >/dev/null 2>&1; then sudo "$@"
    else echo "need root (or sudo) to run: $*" >&2; return 1
    fi
}

apt_install() {
    _as_root env DEBIAN_FRONTEND=noninteractive apt-get update -q >/dev/null &&
        _as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -q "$@" >/dev/null
}

# npm ci, unless node_modules already holds exactly this package-lock.json; Node.js + npm via apt-get.
install_viewer() {
    if ! command -v npm >/dev/null 2>&1 || ! command -v node >/dev/null 2>&1; then
        echo "installing Node.js and npm (apt-get install nodejs npm) for the web viewer" >&2
        apt_install nodejs npm || return 1
    fi
    local stamp=node_modules/.omnisplat-lock.sha256 want
    want="$(sha256sum package-lock.json | cut -d' ' -f1)"
    if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
        return 0
    fi
    npm ci --no-audit --no-fund --loglevel=error >&2 && echo "$want" > "$stamp"
}

# Debian's chromium for the browser test (puppeteer-core drives /usr/bin/chromium; no browser download).
install_chromium() {
    if command -v chromium >/dev/null 2>&1; then
        return 0
    fi
    echo "installing chromium (apt-get install chromium) for the viewer's browser test" >&2
    apt_install chromium
}
