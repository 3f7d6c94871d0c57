#!/usr/bin/env bash
# Networks against SZ3 and ZFP from about 100:1 to 10,000:1 on one volume (issue 15's crossover), as
# docs/results_compress_packed_*.md were made: a small model (2,000 iterations) packed at 0.1 dB, at 1,000:1
# and 3,000:1, with a bounded variant, and models that `train --ratio` sizes for 300:1 to 10,000:1 (all the
# paper's APMGSRN); the default model (hybrid small) packed the same four ways; SZ3 and
# ZFP at relative error bounds from 0.5 (to reach the highest ratios) down to 0.001, and ZFP's
# fixed-precision mode at 1-8 bit planes (bench compress's default precisions).
#
#   bash benchmarks/compress_crossover.sh ../shared/data/miranda_density_256.nc density 0.12 OUT
#
# VARIABLE "-" for a file of one unnamed variable (raw). The third argument is the bounded variant's
# --max-error in data units (about 4 % of the value range in docs/results_compress_crossover.md).
# OUT gets the models and `apmgsrn bench compress`'s CSV, table and chart (compress_NAME.*). Models that
# exist are reused, so a run that stopped goes on where it was.
set -euo pipefail
data=$1 variable=$2 max_error=$3 out=$4
cd "$(dirname "$0")/.."
apm=(env PYTHONPATH="$PWD/src" .venv/bin/python -m apmgsrn)
var=(--variable "$variable") spec="$data:$variable"
[ "$variable" = "-" ] && var=() spec="$data"
train=("${var[@]}" --iterations 2000 --batch-size 32768 --device cpu --seed 0)
mkdir -p "$out"
# Each model is made once; one that cannot be made at this size (a ratio too high for the smallest model
# the decoder allows on a small volume) is skipped with the reason, and the comparison goes on without it.
make() {  # make FILE COMMAND...
  local file=$1; shift
  [ -f "$file" ] || "$@" --out "$file" || echo "skipped $(basename "$file"): the command above failed" >&2
}
pack_four() {  # pack_four MODEL PREFIX: at the 0.1 dB budget, at 1,000:1 and 3,000:1, and bounded at 1,000:1
  local model=$1 prefix=$2
  make "$out/${prefix}packed.apmgsrn" "${apm[@]}" pack "$model" "$data" "${var[@]}"
  for ratio in 1000 3000; do
    make "$out/${prefix}packed_r$ratio.apmgsrn" "${apm[@]}" pack "$model" "$data" "${var[@]}" --ratio $ratio
  done
  make "$out/${prefix}bounded_r1000.apmgsrn" "${apm[@]}" pack "$model" "$data" "${var[@]}" --ratio 1000 \
    --max-error "$max_error"
}
make "$out/small.apmgsrn" "${apm[@]}" train "$data" "${train[@]}" --model apmgsrn --preset small
pack_four "$out/small.apmgsrn" ""
for ratio in 300 1000 3000; do
  make "$out/train_r$ratio.apmgsrn" "${apm[@]}" train "$data" "${train[@]}" --ratio $ratio
done
make "$out/train_r10000.apmgsrn" "${apm[@]}" train "$data" "${train[@]}" --ratio 10000
# The default model (hybrid small), packed the same ways.
make "$out/hybrid.apmgsrn" "${apm[@]}" train "$data" "${train[@]}" --model hybrid --preset small
pack_four "$out/hybrid.apmgsrn" hybrid_
models=()
for name in small packed packed_r1000 packed_r3000 bounded_r1000 train_r300 train_r1000 train_r3000 train_r10000 \
            hybrid hybrid_packed hybrid_packed_r1000 hybrid_packed_r3000 hybrid_bounded_r1000; do
  [ -f "$out/$name.apmgsrn" ] && models+=("$out/$name.apmgsrn")
done
"${apm[@]}" bench compress "$spec" --model-files "${models[@]}" \
  --bounds 0.5 0.3 0.2 0.1 0.05 0.02 0.01 0.005 0.002 0.001 --query-points 65536 --device cpu --out "$out"
