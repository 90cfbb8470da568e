# Sourced by train.sh, ship.sh and ablations.sh: where run folders live.
# run_dir NAME|PATH prints the run folder: a path (containing /) as given; a bare name as
# runs/NAME beside the checkout (gitignored), or scripts/train_default/NAME when a run
# already lives there (a run started before run folders moved out of the tree).
# SEKD_RUNS overrides the runs/ folder.
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
RUNS=${SEKD_RUNS:-$ROOT/runs}
run_dir() {
  case $1 in
    */*) echo "$1" ;;
    *) if [ -f "$ROOT/scripts/train_default/$1/state.json" ]; then echo "$ROOT/scripts/train_default/$1"
       else echo "$RUNS/$1"; fi ;;
  esac
}
