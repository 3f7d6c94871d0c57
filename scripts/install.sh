#!/usr/bin/env bash
# Create .venv at the repo root (if missing) and install apmgsrn into it.
# Usage: scripts/install.sh [EXTRAS]   e.g. scripts/install.sh test
set -euo pipefail
cd "$(dirname "$0")/.."
extras="${1:-}"
if [ ! -x .venv/bin/python ]; then
  python3 -m venv .venv
fi
py=.venv/bin/python
$py -m pip install -q --upgrade pip >/dev/null 2>&1 || true
# Torch first, pinned: an open range would pull a multi-GB CUDA build on a machine without torch.
if ! $py -c "import torch" >/dev/null 2>&1; then
  $py -m pip install -q torch==2.13.0
fi
if [ -n "$extras" ]; then
  $py -m pip install -q -e ".[$extras]"
else
  $py -m pip install -q -e .
fi
