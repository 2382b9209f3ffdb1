#!/usr/bin/env bash
# One-time set-up on a fresh machine (idempotent): libLLVM >= 16 for Dr.Jit's LLVM backend,
# then this package with its dependencies. Safe to run before every command.
set -euo pipefail
cd "$(dirname "$0")/.."

have_llvm() {
    # any libLLVM whose major version is >= 16
    for f in /usr/lib/*/libLLVM*.so* /usr/lib/libLLVM*.so* /usr/lib/llvm-*/lib/libLLVM*.so*; do
        [ -e "$f" ] || continue
        v=$(basename "$f" | sed -n 's/^libLLVM[-.]\(so\.\)\{0,1\}\([0-9][0-9]*\).*/\2/p')
        [ -n "$v" ] && [ "$v" -ge 16 ] && return 0
    done
    return 1
}

apt_install() {
    # apt-get install "$@" (with sudo when not root), updating the package lists only if needed
    local SUDO=""
    [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null && SUDO="sudo"
    export DEBIAN_FRONTEND=noninteractive
    $SUDO apt-get install -y -q "$@" >/dev/null 2>&1 || {
        $SUDO apt-get update -q >/dev/null && $SUDO apt-get install -y -q "$@" >/dev/null; }
}

if ! have_llvm; then
    echo "setup: installing libllvm19 (Dr.Jit needs libLLVM >= 16)" >&2
    apt_install libllvm19
    have_llvm || { echo "setup: no libLLVM >= 16 after installing libllvm19" >&2; exit 1; }
fi

# Headless Chromium for the browser tests of tools/explore.py (Playwright drives this system
# browser; it cannot download its own here).
if ! command -v chromium >/dev/null && ! command -v chromium-browser >/dev/null; then
    echo "setup: installing chromium (browser tests of tools/explore.py)" >&2
    apt_install chromium
    command -v chromium >/dev/null || { echo "setup: chromium did not install" >&2; exit 1; }
fi

python3 -m pip install -q --disable-pip-version-check --root-user-action=ignore -e ".[test,docs]"
python3 -c "import mitsuba_manifold, mitsuba, drjit, starlette, uvicorn, playwright" || { echo "setup: the package does not import" >&2; exit 1; }
