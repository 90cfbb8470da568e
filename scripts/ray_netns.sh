# Sourced by the Ray benchmarks (bench_ray.sh, bench_ray_reconstruct.sh): their cluster runs inside a network
# namespace of its own (loopback only), so every process in it is theirs.

ray_netns_stop() {  # ray_netns_stop NS TEMP: stop the namespace's processes by PID, then remove it and TEMP
  local ns=$1 temp=$2 sig pid
  for sig in TERM KILL; do
    for pid in $(ip netns pids "$ns" 2>/dev/null); do kill -s "$sig" "$pid" 2>/dev/null || true; done
    sleep 2
  done
  ip netns del "$ns" 2>/dev/null || true
  rm -rf "$temp"
}
