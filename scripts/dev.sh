#!/usr/bin/env bash
# One entry point for a fresh Debian machine with Python 3.11 (run as root or with sudo):
#   bash scripts/dev.sh demo   -> set up, then run the demo audit on simulated data
#   bash scripts/dev.sh test   -> set up, then run the test suite
#   bash scripts/dev.sh setup  -> set up only
set -euo pipefail
cd "$(dirname "$0")/.."
VENV="${LABELAUDIT_VENV:-.venv}"

ensure_system_libs() {
    # Open3D's wheel links against libusb-1.0 and will not import without it.
    # (no grep -q: with pipefail, its early exit would fail the pipeline through SIGPIPE)
    if ! ldconfig -p 2>/dev/null | grep 'libusb-1.0.so.0' >/dev/null; then
        echo "installing libusb-1.0-0 (needed by Open3D)" >&2
        local SUDO=""
        [ "$(id -u)" -ne 0 ] && SUDO="sudo"
        $SUDO apt-get update -qq >&2
        DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libusb-1.0-0 >&2
    fi
}

ensure_browser() {
    # The report's browser test (tests/test_viz_browser.py) drives the system Chromium; Playwright
    # never downloads a browser of its own here.
    if ! command -v chromium >/dev/null 2>&1; then
        echo "installing chromium (for the report's browser test)" >&2
        local SUDO=""
        [ "$(id -u)" -ne 0 ] && SUDO="sudo"
        { $SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq chromium; } >&2 \
            || echo "could not install chromium: the browser test will be skipped" >&2
    fi
}

ensure_venv() {
    if [ ! -x "$VENV/bin/python" ]; then
        python3 -m venv "$VENV" >&2
    fi
    local stamp="$VENV/.labelaudit-installed"
    if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
        "$VENV/bin/python" -m pip install -q --upgrade pip >&2
        "$VENV/bin/python" -m pip install -q -e ".[test]" >&2
        touch "$stamp"
    fi
}

ensure_kernels() {
    # The compiled loops, compiled ahead of time into one extension module (needs gcc): a worker
    # then starts without numba's JIT set-up (about 1 s less per process). Rebuilt when a kernel
    # source changed; if it cannot be built, numba's JIT runs them (same results, slower start).
    if [ "$("$VENV/bin/python" -m labelaudit.kernels status | cut -d: -f1)" != "aot" ]; then
        echo "compiling the kernels ahead of time (about a minute, once)" >&2
        "$VENV/bin/python" -m labelaudit.kernels build >&2 \
            || echo "could not compile the kernels ahead of time: numba's JIT runs them (same results)" >&2
    fi
    "$VENV/bin/python" -m compileall -q labelaudit >&2 || true  # bytecode even where PYTHONDONTWRITEBYTECODE is set
}

cmd="${1:-setup}"
shift || true
ensure_system_libs
ensure_venv
ensure_kernels
case "$cmd" in
    setup) echo "ready: $VENV/bin/labelaudit --help" >&2 ;;
    demo) exec "$VENV/bin/labelaudit" demo "$@" ;;
    test) ensure_browser; exec "$VENV/bin/python" -m pytest -q "$@" ;;
    *) echo "usage: bash scripts/dev.sh [setup|demo|test] [args...]" >&2; exit 2 ;;
esac
