#!/usr/bin/env bash
# Install apmgsrn with its test extras into .venv and run the test suite (CPU tier; GPU, browser and
# ParaView tests run where a CUDA device / Debian chromium / Debian ParaView is present, and are skipped
# otherwise).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh test
# The viewer's browser tests drive Debian's chromium; install it when missing (they skip if this fails).
if [ ! -x /usr/bin/chromium ] && command -v apt-get >/dev/null 2>&1; then
  { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium; } >/dev/null 2>&1 \
    || echo "note: could not install chromium; browser tests will be skipped" >&2
fi
# The colour-map tests compare with ParaView's own pvpython; install Debian's paraview when missing (they
# skip if this fails).
if ! command -v pvpython >/dev/null 2>&1 && command -v apt-get >/dev/null 2>&1; then
  { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq paraview; } >/dev/null 2>&1 \
    || echo "note: could not install paraview; ParaView comparison tests will be skipped" >&2
fi
exec .venv/bin/python -m pytest -q -m "not slow" "$@"
