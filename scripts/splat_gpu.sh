#!/usr/bin/env bash
# On a machine with an NVIDIA GPU: install gsplat (after torch), run the CUDA backend's tests and the CUDA
# training benchmark (our trainer against gsplat's own loop, bench/splat_cuda.py).
#   bash scripts/splat_gpu.sh                   # renders the synthetic `small` preset, 1000 steps each
#   bash scripts/splat_gpu.sh --preset tiny     # any bench/splat_cuda.py options
# gsplat from PyPI compiles its CUDA kernels on first use (nvcc needed, minutes); TORCH_EXTENSIONS_DIR
# keeps them for later runs.
set -euo pipefail
cd "$(dirname "$0")/.."
[ -x .venv/bin/python ] || bash scripts/setup.sh
PY=.venv/bin/python
"$PY" -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 'splat_gpu: torch sees no CUDA device')"
"$PY" -c "import gsplat" 2>/dev/null || "$PY" -m pip install gsplat   # after torch, so it builds against it
"$PY" -m pytest tests/test_splat_cuda.py -q -rs
"$PY" bench/splat_cuda.py --out runs/bench/splat_cuda.json "$@"
