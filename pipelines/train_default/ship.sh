#!/usr/bin/env bash
# Ship the run's best model as the package's embedded default and regenerate its model card.
# Refused when the checkpoint misses the regression guard (v_graffiti 1-2 within 3 px):
# pick another with --which models/<task>.pth, or --which auto: the best-validated step that passes.
# Run after train.sh (RUN=<folder name> as for train.sh; default run); then re-run the
# benchmarks (pipelines/paper_benchmarks.sh).
set -euo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
ROOT=$(cd "$HERE/../.." && pwd)
export SEKD_SHARED=$(cd "${SEKD_SHARED:-$ROOT/../shared}" && pwd)
cd "$ROOT"
python -m sekd_sfm.train.ship "pipelines/train_default/${RUN:-run}" --dest sekd_sfm/models/sekd_default.pth \
    --card docs/model_card.md --reference "$SEKD_SHARED/weights/sekd/sekd.pth" "$@"
