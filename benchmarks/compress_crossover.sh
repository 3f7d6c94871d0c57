#!/usr/bin/env bash
# Networks against SZ3 and ZFP from about 100:1 to 10,000:1 on one volume (issue 15's crossover), as
# docs/results_compress_packed_*.md were made: a small model (2,000 iterations) packed at 0.1 dB, at 1,000:1
# and 3,000:1, with a bounded variant, and models that `train --ratio` sizes for 3,000:1 and 10,000:1.
#
#   bash benchmarks/compress_crossover.sh ../shared/data/miranda_density_256.nc density 0.12 OUT
#
# The third argument is the bounded variant's --max-error in data units (HCCI's run used 0.5, about 4 % of
# its value range).
# OUT gets the models and `apmgsrn bench compress`'s CSV, table and chart (compress_NAME.*). Models that
# exist are reused, so a run that stopped goes on where it was.
set -euo pipefail
data=$1 variable=$2 max_error=$3 out=$4
cd "$(dirname "$0")/.."
apm=(env PYTHONPATH="$PWD/src" .venv/bin/python -m apmgsrn)
train=(--variable "$variable" --iterations 2000 --batch-size 32768 --device cpu --seed 0)
mkdir -p "$out"
[ -f "$out/small.apmgsrn" ] || "${apm[@]}" train "$data" "${train[@]}" --preset small --out "$out/small.apmgsrn"
[ -f "$out/packed.apmgsrn" ] || "${apm[@]}" pack "$out/small.apmgsrn" "$data" --variable "$variable" --out "$out/packed.apmgsrn"
for ratio in 1000 3000; do
  [ -f "$out/packed_r$ratio.apmgsrn" ] || "${apm[@]}" pack "$out/small.apmgsrn" "$data" --variable "$variable" --ratio $ratio --out "$out/packed_r$ratio.apmgsrn"
done
[ -f "$out/bounded_r1000.apmgsrn" ] || "${apm[@]}" pack "$out/small.apmgsrn" "$data" --variable "$variable" --ratio 1000 --max-error "$max_error" --out "$out/bounded_r1000.apmgsrn"
[ -f "$out/train_r3000.apmgsrn" ] || "${apm[@]}" train "$data" "${train[@]}" --ratio 3000 --out "$out/train_r3000.apmgsrn"
[ -f "$out/train_r10000.apmgsrn" ] || "${apm[@]}" train "$data" "${train[@]}" --ratio 10000 --grids 8 --width 32 --out "$out/train_r10000.apmgsrn"
"${apm[@]}" bench compress "$data:$variable" --model-files "$out"/small.apmgsrn "$out"/packed.apmgsrn \
  "$out"/packed_r1000.apmgsrn "$out"/packed_r3000.apmgsrn "$out"/bounded_r1000.apmgsrn "$out"/train_r3000.apmgsrn \
  "$out"/train_r10000.apmgsrn --bounds 0.2 0.1 0.05 0.02 0.01 0.005 0.002 0.001 --query-points 65536 --device cpu --out "$out"
