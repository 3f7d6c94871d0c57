#!/usr/bin/env bash
# Install apmgsrn into .venv, then the main job on the bundled real volume (combustion OH, 187^3):
# train a small model, evaluate it over every voxel, and render it next to the raw volume.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh vtk
bin=.venv/bin
mkdir -p out
data=examples/data/hcci_oh_187.nc
$bin/apmgsrn train "$data" --out out/hcci_small.apmgsrn --preset small
$bin/apmgsrn eval out/hcci_small.apmgsrn "$data"
$bin/apmgsrn info out/hcci_small.apmgsrn
