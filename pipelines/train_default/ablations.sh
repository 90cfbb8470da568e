#!/usr/bin/env bash
# The paper's Table 4 ablations with our own training: the default model's run (train.sh:
# cpu schedule, seed 0, the 256 shared COCO photos) with one switch off each.
# Usage: pipelines/train_default/ablations.sh [SWITCH ...]   (default: all four, in order)
# Resumable: run it again to continue each run where it stopped. Run folders: ablations/<switch>/.
set -euo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
export SEKD_SHARED=$(cd "${SEKD_SHARED:-$HERE/../../../shared}" && pwd)
SWITCHES=("$@")
[ ${#SWITCHES[@]} -gt 0 ] || SWITCHES=(no_affine no_desc_dis no_desc_rep no_det_rep)
for switch in "${SWITCHES[@]}"; do
  RUN=$HERE/ablations/$switch
  if [ -f "$RUN/state.json" ]; then
    sekd evolve --out "$RUN" --resume --no-progress
  else
    sekd evolve --images "$SEKD_SHARED/data/train/coco" --schedule cpu --seed 0 --out "$RUN" \
        --set "$switch=true" --no-progress
  fi
done
