#!/bin/bash
# The runs behind docs/results_baselines.md: APMGSRN, fVSRN and NGP under the CPU protocol (2,000 iterations
# x 32,768 points, lr 0.01), then the networks against SZ3 and ZFP. Run from the repository root with
# ../shared/data beside it. Every finished run is a row of bench-results/quality.csv: rerunning this script
# (or the same commands with more --seeds or volumes) only trains what is missing.
#
# OMP_NUM_THREADS=1 gave steadier timings on a shared 2-core machine; drop it on a machine of your own.
set -e
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
D=../shared/data
OUT=${OUT:-bench-results}
SEEDS=${SEEDS:-3}
Q="--iterations 2000 --batch-size 32768 --seeds $SEEDS --out $OUT"

apmgsrn bench quality $D/hcci_oh_187.nc:oh $D/miranda_density_256.nc:density \
  --models apmgsrn fvsrn ngp --sizes small medium $Q
apmgsrn bench compress $D/hcci_oh_187.nc:oh --model-files $OUT/models/hcci_oh_187-oh_*_s0_i2000.apmgsrn --out $OUT
apmgsrn bench compress $D/richtmyer_meshkov_t20_256x256x256_uint8.raw --out $OUT
apmgsrn bench quality $D/channel_pressure_640x240x48.nc:pressure $D/richtmyer_meshkov_t20_256x256x256_uint8.raw \
  $D/c60_128x128x128_uint8.raw $D/neghip_64x64x64_uint8.raw $D/viscous_fingers_t050.vti \
  $D/cth_armor_penetration.vtr:Pressure --models apmgsrn fvsrn ngp --sizes small --seeds 1 \
  --iterations 2000 --batch-size 32768 --out $OUT
apmgsrn bench quality $D/darkmatter_density_64.h5 --transform log10 --models apmgsrn fvsrn ngp --sizes small \
  --seeds 1 --iterations 2000 --batch-size 32768 --out $OUT-log10
apmgsrn bench quality $D/hcci_oh_187.nc:oh --models fvsrn --sizes small --lr-schedule steps \
  --iterations 2000 --batch-size 32768 --out $OUT/steps
apmgsrn grids $OUT/models/hcci_oh_187-oh_apmgsrn_small_s0_i2000.apmgsrn $D/hcci_oh_187.nc --variable oh \
  --out $OUT/grids_hcci_small
