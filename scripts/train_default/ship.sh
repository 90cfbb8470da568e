#!/usr/bin/env bash
# Ship a run's model as the package's embedded default and regenerate its model card.
# Refused when the checkpoint misses the regression guard (v_graffiti 1-2 within 3 px):
# pick another with --which models/<task>.pth, or --which auto: the best-validated step that passes.
# Usage: [RUN=name|path] scripts/train_default/ship.sh [--which best.pth|auto|models/<task>.pth|SOUP.pth]
# (SOUP.pth: a weight average of the run's step models, python -m sekd_sfm.train.soup)
# (RUN as for train.sh, default runs/default); then re-run scripts/paper_benchmarks.sh.
set -euo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
source "$HERE/_run_dir.sh"
export SEKD_SHARED=$(cd "${SEKD_SHARED:-$ROOT/../shared}" && pwd)
RUN=$(run_dir "${RUN:-default}")
cd "$ROOT"
python -m sekd_sfm.train.ship "$RUN" --dest sekd_sfm/model/checkpoints/sekd_own.pth \
    --card docs/model_card.md --reference "$SEKD_SHARED/weights/sekd/sekd.pth" "$@"
