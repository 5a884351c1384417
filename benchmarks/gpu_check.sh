#!/usr/bin/env bash
# One command for a GPU machine (under 5 minutes): installs what the check needs, then holds the torch
# vote kernel on CUDA against the numba kernel and times both at 140k, 560k and 1.12M Gaussians (gpu_check.py).
# Uses the project venv when it exists, else a system python3 that has CUDA torch, numba, scipy and yaml (a GPU
# machine's image, which may reach no package index), else a fresh venv with the pinned torch, numba and friends.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ -x .venv/bin/python ]; then
  py=.venv/bin/python
elif python3 -c "import torch, numba, scipy, yaml; assert torch.cuda.is_available()" 2>/dev/null; then
  py=python3
else
  python3 -m venv /tmp/monovoc_gpu_venv
  py=/tmp/monovoc_gpu_venv/bin/python
  grep -E '^(torch|numba|numpy|scipy|pillow|colour-science|plyfile)==' requirements.txt \
    | "$py" -m pip install --quiet -r /dev/stdin
fi
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
exec "$py" benchmarks/gpu_check.py
