#!/usr/bin/env bash
# Ray versus local extraction throughput on one machine, and the driver's capacity (key rows, final merge).
#
# Starts a two-raylet Ray cluster (1 CPU each) inside a network namespace (loopback only,
# so nothing binds an outward address; needs root and iproute2), then extracts the same
# photos with `--executor local` and `--executor ray`, alternately, ROUNDS times each, and
# measures how many results per second the driver can save (the merge side), to project
# the scaling to 8, 64 and 512 workers. Wall-clock rates depend on what else the machine
# runs; CPU seconds per image (cgroup v1 cpuacct: every process of the local run, or of the
# whole Ray cluster and its driver) do much less, and give Ray's overhead in CPU.
# Results: $OUT/bench_ray.txt (numbers in docs/cluster.md).
#
# Usage: scripts/bench_ray.sh [N_IMAGES [RESIZE_MAX]]
#   IMAGES=folder   photos to extract (default: $SEKD_SHARED/data/train/coco)
#   OUT=folder      work folder (default: a new temporary folder)
#   ROUNDS=2        local/ray pairs of runs
set -euo pipefail

N=${1:-200}
RESIZE=${2:-640}
ROUNDS=${ROUNDS:-2}
SHARED=${SEKD_SHARED:-$(cd "$(dirname "$0")/../.." && pwd)/shared}
IMAGES=${IMAGES:-$SHARED/data/train/coco}
OUT=${OUT:-$(mktemp -d)}
NS=sekdbench$$
PORT=$((21000 + $$ % 20000))
TEMP=/tmp/sekdbench$$
CG=/sys/fs/cgroup/cpuacct/sekdbench$$   # CPU accounting of each side
mkdir -p "$OUT/images"
REPORT="$OUT/bench_ray.txt"

source "$(dirname "$0")/ray_netns.sh"
stop() { ray_netns_stop "$NS" "$TEMP"; rmdir "$CG/local" "$CG/ray" "$CG" 2>/dev/null || true; }
trap stop EXIT

set +o pipefail  # head stops reading early, which ends ls with SIGPIPE: not a failure
ls "$IMAGES" | grep -iE '\.(jpe?g|png)$' | head -n "$N" | while read -r f; do ln -sf "$IMAGES/$f" "$OUT/images/$f"; done
set -o pipefail
COUNT=$(ls "$OUT/images" | wc -l)

mkdir -p "$CG/local" "$CG/ray"
in_cg() { local group=$1; shift; sh -c 'echo $$ > "$0/cgroup.procs"; shift; exec "$@"' "$CG/$group" - "$@"; }
cpu() { cat "$CG/$1/cpuacct.usage"; }   # nanoseconds

ip netns add "$NS"
ip netns exec "$NS" ip link set lo up
COMMON=(--num-cpus 1 --object-store-memory $((1 << 30)) --disable-usage-stats)
in_cg ray ip netns exec "$NS" ray start --head --port "$PORT" --include-dashboard=false --temp-dir "$TEMP" "${COMMON[@]}" >"$OUT/ray_head.log" 2>&1
in_cg ray ip netns exec "$NS" ray start --address "127.0.0.1:$PORT" "${COMMON[@]}" >"$OUT/ray_node.log" 2>&1

run() {  # run NAME GROUP CMD...: "wall-clock-seconds cpu-seconds" of one extraction into $OUT/NAME.h5
  local name=$1 group=$2; shift 2
  local t0 t1 c0 c1
  c0=$(cpu "$group"); t0=$(date +%s.%N)
  in_cg "$group" "$@" "$OUT/images" -o "$OUT/$name.h5" --resize-max "$RESIZE" --overwrite --no-progress \
    2>"$OUT/$name.log" >/dev/null
  t1=$(date +%s.%N); c1=$(cpu "$group")
  echo "$(echo "$t1 - $t0" | bc -l) $(echo "($c1 - $c0) / 10^9" | bc -l)"
}
row() {  # row NAME "WALL CPU" [NOTE]
  set -- "$1" $2 "${3:-}"
  printf "%-8s %8.1f %9.3f %8.1f %8.2f  %s\n" "$1" "$2" "$(echo "$COUNT / $2" | bc -l)" "$3" \
    "$(echo "$3 / $COUNT" | bc -l)" "$4" | tee -a "$REPORT"
}

{
  echo "# sekd extract: $COUNT photos at --resize-max $RESIZE; $(nproc) cores; $(date -u +%FT%TZ)"
  echo "# local = --executor local (torch threads on all cores, the default); local-1t = --num-threads 1 (one core);"
  echo "# ray = --executor ray: 2 raylets x 1 CPU, 2 workers x 1 thread, in netns $NS"
  echo "# load average before: $(cut -d' ' -f1-3 /proc/loadavg)"
  printf "%-8s %8s %9s %8s %8s  %s\n" run seconds images/s cpu-s cpu-s/img "(ray: the driver's own summary)"
} | tee "$REPORT"
for round in $(seq "$ROUNDS"); do
  row "local$round" "$(run "local$round" local sekd extract)"
  row "1t-$round" "$(run "1t-$round" local sekd extract --num-threads 1)"
  r=$(run "ray$round" ray ip netns exec "$NS" sekd extract --executor ray --ray-address "127.0.0.1:$PORT")
  row "ray$round" "$r" "$(grep -o "Ray: [0-9].*" "$OUT/ray$round.log" | tail -1)"
done
echo "# load average after: $(cut -d' ' -f1-3 /proc/loadavg)" | tee -a "$REPORT"

# Same files? Ray workers run 1 torch thread, so they must equal --num-threads 1 byte for byte;
# torch's last bits depend on the thread count, so the default local run may differ in a few images.
python - "$OUT/1t-1.h5" "$OUT/ray1.h5" "$OUT/local1.h5" <<'EOF' | tee -a "$REPORT"
import sys, h5py
def contents(path):
    out = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda n, o: out.__setitem__(n, o[()].tobytes()) if isinstance(o, h5py.Dataset) else None)
    return out
one, ray, default = (contents(p) for p in sys.argv[1:])
print("identical arrays ray1 vs local --num-threads 1:", one == ray, f"({len(one)} arrays)")
print("images differing between local (2 threads) and local --num-threads 1:",
      len({k.split("/")[0] for k in one if one[k] != default.get(k)}))
EOF

# Driver capacity. Workers write their results themselves (one part chunk, or with
# --ray-merge virtual one shard, per task of 4 images) and send the driver only keys, so the
# driver's costs are: (1) the final merge into the HDF5 file, copy against virtual, measured
# on local1.h5's arrays repeated to 2,000 images (scripts/bench_merge.py; the workers'
# writing time is given too: it is spread over the workers), and (2) absorbing key rows from
# the actor pool (identity workers returning key rows, no model, through ray_pool._stream: the
# whole driver side of a run with free workers; CPU of the driver process per row, Ray's
# threads included).
python "$(dirname "$0")/bench_merge.py" "$OUT/local1.h5" --images 2000 --work "$OUT/merge" | tee -a "$REPORT"
# ... and in tasks of 64 images, the task size of a 512-worker cluster (execution.task_size)
python "$(dirname "$0")/bench_merge.py" "$OUT/local1.h5" --images 2048 --task 64 --work "$OUT/merge" | tee -a "$REPORT"

RAY_BACKEND_LOG_LEVEL=fatal ip netns exec "$NS" python - "127.0.0.1:$PORT" <<'EOF' | tee -a "$REPORT"
import logging, pickle, sys, time
import ray
from sekd_sfm.execution import RayOptions
from sekd_sfm.execution.ray_pool import _columns, _stream, _workers
from sekd_sfm.execution.ray_run import _rows
ray.init(address=sys.argv[1], log_to_driver=False, logging_level=logging.WARNING)
class Echo:  # a worker that answers at once with the rows a real worker sends: keys, no errors, its chunk name
    def __call__(self, batch):
        keys = [str(k) for k in batch["key"]]
        return _rows(keys, [""] * len(keys), f"{time.time_ns():020d}-12345-0123456789abcdef-000001.npz")
n = 4000
for per_task in (4, 32):  # the driver's cost is per task, so bigger tasks divide it
    items = [{"key": f"folder/image_{i:06d}.jpg"} for i in range(n)]
    first = None; count = 0; size = 0; chunks = set()
    options = RayOptions(images_per_task=per_task)
    tasks = [_columns(items[i:i + per_task]) for i in range(0, n, per_task)]
    with _stream(ray, tasks, Echo, (), min(_workers(ray, options), len(tasks)), options) as results:
        for batch in results:  # as sekd_sfm.execution.ray_run._drain reads them
            if first is None:
                first, cpu0, skip = time.perf_counter(), time.process_time(), len(batch["key"])
            size += len(pickle.dumps(batch, protocol=pickle.HIGHEST_PROTOCOL))
            chunks.update(batch["chunk"])
            count += len(batch["key"])
    t1, cpu = time.perf_counter(), time.process_time() - cpu0
    rows = count - skip
    print(f"actor pool to driver: {count} key rows ({size / count:.0f} B each) in tasks of {per_task}: {rows / (t1 - first):.0f} "
          f"rows/s after the first task (2 echo workers, same 2 cores); driver CPU {1000 * cpu / rows:.3f} ms per row, "
          f"{1000 * cpu * per_task / rows:.2f} ms per task = {rows / cpu:.0f} rows per CPU-second of the driver")
EOF
echo "report: $REPORT"
