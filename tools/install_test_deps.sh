#!/usr/bin/env bash
# Install what meshseq's tests need besides Python packages, only where missing (idempotent;
# a second run with everything present takes well under a second and touches nothing):
#   - the Khronos glTF validator (npm package gltf-validator, run with node) into tools/node_modules
#     (gitignored), for tests/test_export.py;
#   - headless Chromium and its WebDriver (Debian packages chromium, chromium-driver), for
#     tests/test_viewer.py;
#   - Mesa's EGL and software OpenGL (Debian packages libegl1, libegl-mesa0, libgl1-mesa-dri),
#     for offscreen rendering with pyrender in tests/test_render.py;
#   - Blender, run headless, with numpy for its Python (Debian packages blender, python3-numpy),
#     the client of the MDD/PC2/glTF files in tests/test_blender.py.
# Debian packages are installed with apt-get when running as root; otherwise the script prints
# the command to run and fails. Set MESHSEQ_NO_APT=1 to never call apt-get.
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
GLTF_VALIDATOR_VERSION="2.0.0-dev.3.10"
VALIDATOR_DIR="$ROOT/tools/node_modules/gltf-validator"

apt_missing=()

# --- Debian packages -------------------------------------------------------------------------
{ [ -x /usr/bin/chromium ] || [ -x /usr/bin/chromium-browser ]; } || apt_missing+=(chromium)
[ -x /usr/bin/chromedriver ] || apt_missing+=(chromium-driver)
have_lib() { ldconfig -p 2>/dev/null | grep -q "$1" || ls /usr/lib/*/"$1"* >/dev/null 2>&1; }
have_lib libEGL.so.1 || apt_missing+=(libegl1)
have_lib libEGL_mesa.so.0 || apt_missing+=(libegl-mesa0)
ls /usr/lib/*/dri/swrast_dri.so >/dev/null 2>&1 || apt_missing+=(libgl1-mesa-dri)
command -v blender >/dev/null 2>&1 || apt_missing+=(blender)
[ -d /usr/lib/python3/dist-packages/numpy ] || apt_missing+=(python3-numpy)
command -v node >/dev/null 2>&1 || apt_missing+=(nodejs)
command -v npm >/dev/null 2>&1 || apt_missing+=(npm)

if [ "${#apt_missing[@]}" -gt 0 ]; then
    if [ "${MESHSEQ_NO_APT:-0}" != "1" ] && [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
        echo "install_test_deps: apt-get install ${apt_missing[*]}"
        apt-get update -qq
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${apt_missing[@]}"
    else
        echo "install_test_deps: missing Debian packages: ${apt_missing[*]}" >&2
        echo "  run: sudo apt-get install --no-install-recommends ${apt_missing[*]}" >&2
        exit 1
    fi
fi

# --- Khronos glTF validator ------------------------------------------------------------------
installed=""
if [ -f "$VALIDATOR_DIR/package.json" ]; then
    installed="$(node -p "require('$VALIDATOR_DIR/package.json').version" 2>/dev/null || true)"
fi
if [ "$installed" != "$GLTF_VALIDATOR_VERSION" ]; then
    echo "install_test_deps: npm install gltf-validator@$GLTF_VALIDATOR_VERSION into tools/node_modules"
    npm install --prefix "$ROOT/tools" --no-save --no-package-lock --no-audit --no-fund --loglevel=error \
        "gltf-validator@$GLTF_VALIDATOR_VERSION"
fi
