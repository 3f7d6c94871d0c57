#!/usr/bin/env bash
# Install apmgsrn with its test extras into .venv, check the layering (import-linter) and run the test suite
# (CPU tier; GPU, browser and ParaView tests run where a CUDA device / Debian chromium / Debian ParaView is
# present, and are skipped otherwise).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh test
# The viewer's browser tests drive Debian's chromium, the colour-map tests compare with ParaView's own
# pvpython: install the Debian packages when missing (those tests skip, with a note here, if this fails).
missing=()
[ -x /usr/bin/chromium ] || missing+=(chromium)
command -v pvpython >/dev/null 2>&1 || missing+=(paraview)
if [ ${#missing[@]} -gt 0 ] && command -v apt-get >/dev/null 2>&1; then
  { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}"; } >/dev/null 2>&1 \
    || echo "note: could not install ${missing[*]}; the tests that need them will be skipped" >&2
fi
# The layering docs/design.md promises (contracts in pyproject.toml).
.venv/bin/lint-imports
exec .venv/bin/python -m pytest -q -m "not slow" "$@"
