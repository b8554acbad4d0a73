#!/usr/bin/env bash
# Set up the project's virtual environment (once) and run it.
#   bash scripts/dev.sh serve [llrs serve arguments] the lab server on the simulated lab: dashboard + REST API
#   bash scripts/dev.sh run   [llrs run arguments]   a few shots on the simulated lab
#   bash scripts/dev.sh test  [pytest arguments]     ruff, mypy and the whole test suite (installs Chromium for the
#                                                    browser test); with arguments, only pytest with them
# Needs only Python 3.11+; installs python3-venv (and, for `test`, chromium) through apt when missing.
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3}
VENV=.venv

ensure_venv() {
    if [ ! -x "$VENV/bin/python" ]; then
        if ! "$PYTHON" -c 'import ensurepip, venv' 2>/dev/null; then
            echo "[dev.sh] $PYTHON has no venv/ensurepip; installing python3-venv with apt" >&2
            SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
            $SUDO apt-get update -qq && $SUDO apt-get install -y -qq python3-venv >/dev/null
        fi
        "$PYTHON" -m venv "$VENV"
    fi
    # Reinstall only when pyproject.toml changed since the last install.
    local stamp="$VENV/.installed-$(sha256sum pyproject.toml | cut -c1-16)"
    if [ ! -f "$stamp" ]; then
        "$VENV/bin/python" -m pip install -q --upgrade pip >/dev/null
        "$VENV/bin/python" -m pip install -q -e '.[dev]'
        rm -f "$VENV"/.installed-*; touch "$stamp"
    fi
}

# The dashboard's browser test drives Debian's Chromium (playwright cannot download browsers here).
ensure_chromium() {
    if [ -x /usr/bin/chromium ] || [ -n "${LLRS_CHROMIUM:-}" ]; then return 0; fi
    echo "[dev.sh] installing Debian's chromium for the dashboard's browser test" >&2
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    if ! { $SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq chromium >/dev/null; }; then
        echo "[dev.sh] could not install chromium; the browser test will be skipped" >&2
    fi
}

cmd=${1:-run}; shift || true
case "$cmd" in
    run)
        ensure_venv
        if [ $# -eq 0 ]; then set -- --config examples/chain-1x64.yaml --shots 20; fi
        exec "$VENV/bin/llrs" run "$@"
        ;;
    serve)
        ensure_venv
        exec "$VENV/bin/llrs" serve "$@"
        ;;
    test)
        ensure_venv
        ensure_chromium
        if [ $# -gt 0 ]; then exec "$VENV/bin/python" -m pytest "$@"; fi
        # The whole check, as CI runs it: lint and types, the default suite, then the benchmarks' short smoke
        # runs (marked ``bench``: left out of the default run because they take tens of seconds). The default
        # suite runs on every core (pytest-xdist), a whole test file to one worker so that each file's
        # module-scoped fixtures (servers, closed-loop runs) are built once; the smoke runs stay in one process,
        # since they measure latency under a load of their own.
        "$VENV/bin/ruff" check .
        "$VENV/bin/mypy"
        "$VENV/bin/python" -m pytest -n auto --dist loadfile
        exec "$VENV/bin/python" -m pytest -m bench
        ;;
    *)
        echo "usage: bash scripts/dev.sh {serve|run|test} [args]" >&2; exit 2
        ;;
esac
