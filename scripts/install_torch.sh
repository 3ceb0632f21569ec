#!/usr/bin/env bash
# Install torch into the given Python without ever pulling a multi-GB CUDA build onto a
# machine that has no GPU:
#   1. torch already importable: nothing to do;
#   2. a local CPU wheel of torch 2.13.0 in pip's find-links (as on this project's machines):
#      `pip install torch==2.13.0` takes it (its small dependencies come from the index);
#   3. an NVIDIA GPU (nvidia-smi present): the default build;
#   4. otherwise PyTorch's CPU-only index.
set -euo pipefail
PY="${1:-python3}"
"$PY" -c "import torch" 2>/dev/null && exit 0
links="${PIP_FIND_LINKS:-} $("$PY" -m pip config get global.find-links 2>/dev/null || true)"
for d in $links; do
  d="${d#file://}"
  if compgen -G "$d/torch-2.13.0*cpu*.whl" >/dev/null; then
    exec "$PY" -m pip install -q "torch==2.13.0"
  fi
done
if command -v nvidia-smi >/dev/null 2>&1; then
  exec "$PY" -m pip install -q torch
fi
exec "$PY" -m pip install -q torch --index-url https://download.pytorch.org/whl/cpu
