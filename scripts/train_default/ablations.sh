#!/usr/bin/env bash
# The paper's Table 4 ablations with our own training: the default model's recipe (the config
# of the run folder BASE, default runs/default from train.sh: the embedded model's recipe, seed 0,
# the 256 shared COCO photos)
# with one switch on each, for ROUNDS rounds (default 2: ~1 h each on 2 cores), then
# `sekd bench homography` of each ablation's best step against the baseline's best step
# within the same rounds (python -m sekd_sfm.train.ablation chooses and checks them).
# Usage: [ROUNDS=2] [BASE=default] [OUT=bench-ablations] scripts/train_default/ablations.sh [SWITCH ...]
#        (default: all four switches, in order; extra sekd evolve options after `--`)
# Resumable: run it again to continue each run where it stopped. Run folders: runs/ablations/<switch>/
# beside the checkout (gitignored; SEKD_RUNS moves runs/). BASE: a run name or path, as RUN in train.sh.
set -euo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
source "$HERE/_run_dir.sh"
export SEKD_SHARED=$(cd "${SEKD_SHARED:-$ROOT/../shared}" && pwd)
ROUNDS=${ROUNDS:-2}
BASE=$(run_dir "${BASE:-default}")
OUT=${OUT:-bench-ablations}
SWITCHES=()
while [ $# -gt 0 ] && [ "$1" != "--" ]; do SWITCHES+=("$1"); shift; done
[ "${1:-}" != "--" ] || shift
[ ${#SWITCHES[@]} -gt 0 ] || SWITCHES=(no_affine no_desc_dis no_desc_rep no_det_rep)
RUNS=()
for switch in "${SWITCHES[@]}"; do
  RUN=$RUNS/ablations/$switch
  RUNS+=("$RUN")
  if [ -f "$RUN/state.json" ]; then
    sekd evolve --out "$RUN" --resume --no-progress "$@"
  else
    sekd evolve --images "$SEKD_SHARED/data/train/coco" --config "$BASE/config.yaml" --out "$RUN" \
        --rounds "$ROUNDS" --set "$switch=true" --no-progress "$@"
  fi
done
SPECS=$(python -m sekd_sfm.train.ablation "$BASE" "${RUNS[@]}")  # fails (and stops) if not comparable
METHODS=()
while read -r spec; do METHODS+=(-m "$spec"); done <<< "$SPECS"
sekd bench homography "${METHODS[@]}" -o "$OUT/homography"
sekd bench summary --homography "$OUT/homography/results.json" -o "$OUT/summary" --highlight ours_full
