#!/usr/bin/env bash
# Train the default model the package embeds: `sekd evolve` with the cpu schedule on the
# 256 shared COCO photos, seed 0 (about 3.75 h of 2-core CPU for 5 rounds). Resumable: run it
# again to continue where it stopped.
# Usage: [RUN=name|path] scripts/train_default/train.sh [sekd evolve options...]
# The run folder is runs/<RUN> beside the checkout (default runs/default; gitignored) or the
# path RUN names; a folder that holds a run is resumed with its own saved config.
set -euo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
source "$HERE/_run_dir.sh"
# The shared data beside the checkout unless SEKD_SHARED says otherwise (validation reads it too).
export SEKD_SHARED=$(cd "${SEKD_SHARED:-$ROOT/../shared}" && pwd)
RUN=$(run_dir "${RUN:-default}")
if [ -f "$RUN/state.json" ]; then
  sekd evolve --out "$RUN" --resume "$@"
else
  sekd evolve --images "$SEKD_SHARED/data/train/coco" --schedule cpu --seed 0 --out "$RUN" "$@"
fi
