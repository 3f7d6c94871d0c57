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
$bin/apmgsrn render out/hcci_small.apmgsrn --out out/hcci_small.png --compare "$data" \
  --width 384 --height 384 --colormap "Cool to Warm" --opacity 0,0,0.15,0,1,0.9
echo "images: out/hcci_small.png (model beside the raw-volume render) and its error image"
