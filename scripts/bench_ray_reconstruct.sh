#!/usr/bin/env bash
# `sekd reconstruct` on a two-raylet Ray cluster against the same run locally, stage by stage.
#
# Generates a city-block walk (`sekd bench scale --generate-only`), starts two raylets of one CPU
# each inside a network namespace (loopback only: nothing binds an outward address; needs root and
# iproute2), then reconstructs the walk with `--executor local --num-threads 1` and with
# `--executor ray --num-threads 1`, ROUNDS times each, alternately. Per run: wall time, the stage
# table of stats.json (seconds, where each stage ran), registered photos and pose AUC@5 against the
# true cameras. The cluster is stopped by the namespace's PIDs, also on failure. ALL_CORES=1 adds,
# each round, the same run locally on every core of this machine (no --num-threads: local worker
# processes, torch and the adjustments on all threads): what this machine gives with every core, the
# reference for the cluster of as many CPUs.
# Results: $OUT/bench_ray_reconstruct.txt and .json (numbers in docs/cluster.md).
#
# Usage: scripts/bench_ray_reconstruct.sh [N_PHOTOS]
#   OUT=folder      work folder (default: a new temporary folder); a scene already there is reused
#   ROUNDS=1        local/ray pairs of runs
#   ALL_CORES=1     also a local run on all cores each round
#   ARGS="..."      more options of both runs, e.g. ARGS="--mapper-type hierarchical --mapper
#                   clustering_options.leaf_max_num_images=50" (clusters of 50 photos, mapped on the workers)
set -euo pipefail

N=${1:-100}
ROUNDS=${ROUNDS:-1}
OUT=${OUT:-$(mktemp -d)}
NS=sekdrecon$$
PORT=$((21000 + $$ % 20000))
TEMP=/tmp/sekdrecon$$
REPORT="$OUT/bench_ray_reconstruct.txt"
mkdir -p "$OUT"

source "$(dirname "$0")/ray_netns.sh"
stop() { ray_netns_stop "$NS" "$TEMP"; }
trap stop EXIT

SCENE="$OUT/scene/n$N/scene"
[ -d "$SCENE/images" ] || sekd bench scale --sizes "$N" --generate-only -o "$OUT/scene" >"$OUT/generate.log" 2>&1

ip netns add "$NS"
ip netns exec "$NS" ip link set lo up
COMMON=(--num-cpus 1 --object-store-memory $((1 << 30)) --disable-usage-stats)
ip netns exec "$NS" ray start --head --port "$PORT" --include-dashboard=false --temp-dir "$TEMP" "${COMMON[@]}" \
  >"$OUT/ray_head.log" 2>&1
ip netns exec "$NS" ray start --address "127.0.0.1:$PORT" "${COMMON[@]}" >"$OUT/ray_node.log" 2>&1

run() {  # run NAME THREADS CMD...: reconstruct the scene into $OUT/NAME (THREADS: --num-threads, "all": none)
  local name=$1 threads=$2; shift 2
  local t0
  rm -rf "${OUT:?}/$name"
  t0=$(date +%s.%N)
  [ "$threads" = all ] || set -- "$@" --num-threads "$threads"
  # shellcheck disable=SC2086  # ARGS: options split on spaces
  "$@" "$SCENE/images" -o "$OUT/$name" --no-progress ${ARGS:-} >"$OUT/$name.log" 2>&1
  echo "$(date +%s.%N) - $t0" | bc -l
}

echo "# sekd reconstruct: $N generated photos; $(nproc) cores; $(date -u +%FT%TZ); load before: $(cut -d' ' -f1-3 /proc/loadavg)" \
  | tee "$REPORT"
WALLS=()
for round in $(seq "$ROUNDS"); do
  WALLS+=("local$round=$(run "local$round" 1 sekd reconstruct)")
  WALLS+=("ray$round=$(run "ray$round" 1 ip netns exec "$NS" sekd reconstruct --executor ray --ray-address "127.0.0.1:$PORT")")
  [ "${ALL_CORES:-0}" = 1 ] && WALLS+=("cores$round=$(run "cores$round" all sekd reconstruct)")
done
echo "# load after: $(cut -d' ' -f1-3 /proc/loadavg)" | tee -a "$REPORT"

export COMMAND="ROUNDS=$ROUNDS ALL_CORES=${ALL_CORES:-0} ARGS=\"${ARGS:-}\" scripts/bench_ray_reconstruct.sh $N"  # the record
python - "$OUT" "$SCENE" "${WALLS[@]}" <<'EOF' | tee -a "$REPORT"
import json, os, sys
from pathlib import Path
from sekd_sfm.bench.scale.covisibility import read_covisibility
from sekd_sfm.bench.scale.run import evaluate_model
from sekd_sfm.bench.scale.scene import read_scene
from sekd_sfm.runtime import run_record, usable_cores

out, scene_dir = Path(sys.argv[1]), Path(sys.argv[2])
walls = dict(arg.split("=") for arg in sys.argv[3:])
scene, covisibility = read_scene(scene_dir), read_covisibility(scene_dir)
runs = {}
for name, wall in walls.items():
    stats = json.loads((out / name / "stats.json").read_text())
    accuracy = evaluate_model(out / name / "model", scene, covisibility)
    runs[name] = {"wall_s": round(float(wall), 1), "registered": accuracy["registered"],
                  "scene_images": accuracy["scene_images"], "auc5": round(accuracy["auc5"], 4),
                  "stages": stats["stages"]}
    print(f"{name:8s} wall {float(wall):7.1f} s  registered {accuracy['registered']}/{accuracy['scene_images']}"
          f"  AUC@5 {accuracy['auc5']:.3f}")
    for row in stats["stages"]:
        print(f"    {row['stage']:<16s} {row['seconds']:8.1f}  {row['ran_on']}")
        for part, seconds in row.get("parts", {}).items():  # e.g. mapping's chain, closing, principal point test
            print(f"      {part:<22s} {seconds:8.1f}")
for round in sorted({name[-1] for name in walls}):
    local, ray, cores = runs.get(f"local{round}"), runs.get(f"ray{round}"), runs.get(f"cores{round}")
    if local and ray:
        print(f"round {round}: Ray {local['wall_s'] / ray['wall_s']:.2f}x faster than local")
    if local and cores:
        print(f"round {round}: local on all {usable_cores()} cores {local['wall_s'] / cores['wall_s']:.2f}x faster "
              "than on one")
record = {**run_record(), "command": os.environ["COMMAND"]}
(out / "bench_ray_reconstruct.json").write_text(json.dumps({"record": record, "runs": runs}, indent=1))
EOF
