#!/usr/bin/env bash
# scanpipe's one entry point: set-up, the main job, the tests. Idempotent; fast the second time.
#   ./run.sh demo [ARGS]   set up, then simulate the built-in room and build the textured model
#   ./run.sh test [ARGS]   set up, then ruff, mypy and the whole test suite (ARGS go to pytest)
#   ./run.sh setup         only the set-up
set -euo pipefail
cd "$(dirname "$0")"
VENV="${SCANPIPE_VENV:-.venv}"

need_system_libs() {
  # Open3D's wheel needs libusb-1.0 and libgomp at import time.
  # Read the cache first: grep -q closing the pipe early would fail the check under pipefail.
  local libs
  libs="$(ldconfig -p 2>/dev/null || true)"
  ! grep -q 'libusb-1.0.so.0' <<<"$libs" || ! grep -q 'libgomp.so.1' <<<"$libs"
}

sudo_prefix() {
  if [ "$(id -u)" = 0 ]; then return 0; fi
  if command -v sudo >/dev/null; then echo sudo; return 0; fi
  echo "run.sh: error: need root (or sudo) to apt-get install system packages" >&2
  exit 1
}

setup() {
  if need_system_libs; then
    echo "run.sh: installing system libraries for Open3D (libusb-1.0-0, libgomp1)" >&2
    $(sudo_prefix) apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $(sudo_prefix) apt-get install -y -qq libusb-1.0-0 libgomp1 \
      >/dev/null
  fi
  local python
  python="$(command -v python3.11 || command -v python3)"
  if ! "$python" -c 'import sys; sys.exit(sys.version_info < (3, 11))'; then
    echo "run.sh: error: Python 3.11 or newer is needed ($python is older)" >&2
    exit 1
  fi
  [ -x "$VENV/bin/python" ] || "$python" -m venv "$VENV"
  local stamp
  stamp="$(cat pyproject.toml | sha256sum | cut -c1-16)"
  if [ "$(cat "$VENV/.setup-stamp" 2>/dev/null)" != "$stamp" ]; then
    echo "run.sh: installing scanpipe and its dependencies into $VENV" >&2
    "$VENV/bin/python" -m pip install -q --upgrade pip
    "$VENV/bin/python" -m pip install -q -e ".[dev,ray]"  # ray: the batch tests on a local Ray
    echo "$stamp" > "$VENV/.setup-stamp"
  fi
}

setup_test_tools() {
  # Debian's Chromium renders the report's 3-D view in the tests (driven by Playwright).
  if ! command -v chromium >/dev/null; then
    echo "run.sh: installing Chromium for the viewer tests" >&2
    $(sudo_prefix) apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $(sudo_prefix) apt-get install -y -qq chromium >/dev/null
  fi
  # Node.js tools the tests run on our files: the Khronos glTF-Validator (GLB) and loaders.gl
  # (a second, independent LAS/LAZ reader).
  local validator=".cache/gltf-validator/node_modules/gltf-validator"
  local loaders=".cache/loaders-gl/node_modules/@loaders.gl/las"
  [ -d "$validator" ] && [ -d "$loaders" ] && return 0
  if ! command -v npm >/dev/null; then
    echo "run.sh: installing Node.js and npm for the glTF-Validator and loaders.gl" >&2
    $(sudo_prefix) apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $(sudo_prefix) apt-get install -y -qq nodejs npm >/dev/null
  fi
  if [ ! -d "$validator" ]; then
    echo "run.sh: installing the Khronos glTF-Validator into .cache/" >&2
    npm install --silent --no-audit --no-fund --prefix .cache/gltf-validator \
      gltf-validator@2.0.0-dev.3.10 >/dev/null
  fi
  if [ ! -d "$loaders" ]; then
    echo "run.sh: installing loaders.gl (LAS reader) into .cache/" >&2
    npm install --silent --no-audit --no-fund --prefix .cache/loaders-gl \
      @loaders.gl/core@4.4.5 @loaders.gl/las@4.5.1 >/dev/null
  fi
}

case "${1:-}" in
  demo)
    shift; setup
    exec "$VENV/bin/scanpipe" demo "$@" ;;
  test)
    shift; setup; setup_test_tools
    "$VENV/bin/ruff" check src tests benchmarks
    "$VENV/bin/mypy" src
    # With no arguments: every test and every notebook (executed by nbmake, outputs not stored).
    if [ "$#" -eq 0 ]; then set -- tests notebooks; fi
    exec "$VENV/bin/pytest" -n 2 --nbmake "$@" ;;
  setup)
    setup ;;
  *)
    sed -n '2,6p' "$0" >&2
    exit 2 ;;
esac
