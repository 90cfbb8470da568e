#!/usr/bin/env bash
# The paper's evaluations on the shared data, every method side by side.
# Usage: scripts/paper_benchmarks.sh [OUT_DIR]   (SEKD_SHARED defaults to ../shared;
#        SKIP_SPEED=1 skips the speed benchmark). The embedded `own` model is `sekd_ours`.
# Re-running is cheap: each benchmark caches its extracted features under OUT_DIR.
set -euo pipefail
OUT=${1:-bench-results}
SHARED=${SEKD_SHARED:-../shared}
W=$SHARED/weights/sekd
SEKD_METHODS=(-m "sekd_authors=sekd:$W/sekd.pth"
              -m "sekd:$W/sekd_wo_affine.pth" -m "sekd:$W/sekd_wo_desc_dist.pth"
              -m "sekd:$W/sekd_wo_desc_rep.pth" -m "sekd:$W/sekd_wo_det_rep.pth")
if python -c "from sekd_sfm.model.weights import EMBEDDED_MODELS as m; raise SystemExit(not m['own'].is_file())"; then
  SEKD_METHODS=(-m "sekd_ours=sekd:own" "${SEKD_METHODS[@]}")  # the embedded `own` model (--model own)
fi
CLASSIC=(-m sift -m orb -m akaze -m brisk -m kaze)
PEERS=(-m disk -m aliked -m xfeat)

[ -n "${SKIP_SPEED:-}" ] || sekd bench speed --weights "$W/sekd.pth" -o "$OUT/speed.json"
sekd bench homography "${CLASSIC[@]}" "${PEERS[@]}" "${SEKD_METHODS[@]}" -o "$OUT/homography"
sekd bench pose "${CLASSIC[@]}" "${PEERS[@]}" "${SEKD_METHODS[@]}" -o "$OUT/pose"
sekd bench sfm fountain-P11 "${CLASSIC[@]}" "${PEERS[@]}" "${SEKD_METHODS[@]}" -o "$OUT/sfm"
sekd bench summary --homography "$OUT/homography/results.json" --pose "$OUT/pose/results.json" \
    --sfm "$OUT/sfm/results.json" -o "$OUT/summary" --highlight sekd_ours --highlight sekd_authors
