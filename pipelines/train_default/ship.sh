#!/usr/bin/env bash
# Ship the run's best model as the package's embedded default and regenerate its model card.
# Run after train.sh; then re-run the benchmarks (pipelines/paper_benchmarks.sh).
set -euo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
ROOT=$(cd "$HERE/../.." && pwd)
export SEKD_SHARED=$(cd "${SEKD_SHARED:-$ROOT/../shared}" && pwd)
cd "$ROOT"
python -m sekd_sfm.train.ship pipelines/train_default/run --dest sekd_sfm/models/sekd_default.pth \
    --card docs/model_card.md "$@"
