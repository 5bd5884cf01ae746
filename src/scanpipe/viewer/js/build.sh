#!/usr/bin/env bash
# Rebuild assets/viewer.bundle.js from viewer.js and the pinned three.js (developers only: the
# bundle is committed, so nothing is downloaded when scanpipe is installed or run).
set -euo pipefail
cd "$(dirname "$0")"
npm ci --no-audit --no-fund
npm run build
cp node_modules/three/LICENSE ../assets/three-LICENSE.txt
# The Draco decoder bundled with it is Apache-2.0: ../assets/draco-LICENSE.txt (kept by hand).
