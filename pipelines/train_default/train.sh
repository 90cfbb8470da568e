#!/usr/bin/env bash
# Train the default model the package embeds: `sekd evolve` with the cpu schedule on the
# 256 shared COCO photos, seed 0. Resumable: run it again to continue where it stopped.
# The run folder lives next to this script (config, state, logs, labels, per-step models):
# run/ by default, or RUN=<folder name> for another run with the current schedule. A folder
# that holds a run is resumed with its own saved config: run (session 1), run_v2 (+ floor of
# 100 reliability keypoints, 8 descriptor epochs), run_v3 (+ spread_weight 1, the embedded
# model's run); a new folder gets today's cpu schedule, which equals run_v3's recipe.
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
