#!/usr/bin/env bash
# Train the default model the package embeds: `sekd evolve` with the cpu schedule on the
# 256 shared COCO photos, seed 0. Resumable: run it again to continue where it stopped.
# The run folder lives next to this script (config, state, logs, labels, per-step models):
# run/ by default, or RUN=<folder name> for another run of the same recipe with the current
# schedule (e.g. RUN=run_v2: the cpu schedule with rel_min_keypoints 100).
set -euo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
# The shared data beside the checkout unless SEKD_SHARED says otherwise (validation reads it too).
export SEKD_SHARED=$(cd "${SEKD_SHARED:-$HERE/../../../shared}" && pwd)
SHARED=$SEKD_SHARED
RUN=$HERE/${RUN:-run}
if [ -f "$RUN/state.json" ]; then
  sekd evolve --out "$RUN" --resume "$@"
else
  sekd evolve --images "$SHARED/data/train/coco" --schedule cpu --seed 0 --out "$RUN" "$@"
fi
