#!/usr/bin/env bash
# Install apmgsrn with its test extras into .venv and run the test suite (CPU tier; GPU and browser
# tests run where a CUDA device / Debian chromium is present, and are skipped otherwise).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh test
exec .venv/bin/python -m pytest -q -m "not slow" "$@"
