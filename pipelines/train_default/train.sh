#!/usr/bin/env bash
# Train the default model the package embeds: `sekd evolve` with the cpu schedule on the
# 256 shared COCO photos, seed 0. Resumable: run it again to continue where it stopped.
# The run folder lives next to this script (config, state, logs, labels, per-step models).
set -euo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
# The shared data beside the checkout unless SEKD_SHARED says otherwise (validation reads it too).
export SEKD_SHARED=$(cd "${SEKD_SHARED:-$HERE/../../../shared}" && pwd)
SHARED=$SEKD_SHARED
RUN=$HERE/run
if [ -f "$RUN/state.json" ]; then
  sekd evolve --out "$RUN" --resume "$@"
else
  sekd evolve --images "$SHARED/data/train/coco" --schedule cpu --seed 0 --out "$RUN" "$@"
fi
