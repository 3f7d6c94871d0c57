#!/usr/bin/env bash
# The rate-distortion page, docs/results_rate_distortion.md (charts in docs/images/rate_distortion_*.png):
# every compressor and the networks (the default model and APMGSRN, `train --ratio`) at 30:1 to 10,000:1
# against float32, on the shared volumes of 128^3 and more that no compressor made and the 128^3 turbulence
# that apmgsrn.bench.simulate computes (once, kept in .bench_data/). CPU protocol, one thread. A compressor
# whose one compression takes over 30 s on a volume is left out there (TTHRESH on the 256^3 volume: 70-110 s a
# compression on a 2-core Xeon, and its ratio search compresses up to 40 times); the page says so.
#
#   bash benchmarks/rate_distortion.sh [OUT] [EXTRA OPTIONS...]     # e.g. OUT --quick, OUT --ratios 100 1000
#
# OUT (default bench-results/rate_distortion) keeps bench compress's CSV of each volume and the models: the
# same command again measures only what is missing (delete OUT/models to train the networks anew).
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-bench-results/rate_distortion}
shift || true
export OMP_NUM_THREADS=1
exec env PYTHONPATH="$PWD/src" .venv/bin/python -m apmgsrn bench rd c60 turbulence-vorticity-128 richtmyer-meshkov \
  --compress-seconds 30 --iterations 2000 --batch-size 32768 --device cpu --out "$out" --page docs/results_rate_distortion.md "$@"
