#!/bin/bash
# The `paper` preset at the paper's budget (issue 35): seed 0 to 3e6 transitions, seeds 1-2
# (vmapped) to 1e6, each in the background at the idle scheduling class (chrt -i 0: it takes
# only CPU that nothing else wants) and nice 19, from a pinned git worktree so that later
# commits never change a run in flight.  Reported by experiments/paper_budget.py.
#
#   bash experiments/paper_budget.sh start    # new runs (refuses if the run directories exist)
#   bash experiments/paper_budget.sh resume   # each from its newest checkpoint
#   bash experiments/paper_budget.sh status   # the last progress line of each log
#
# Environment (defaults in brackets): LONGRUNS [/work/longruns] holds the run directories, logs
# and the compilation cache; WORKTREE [/work/lr-paper] the pinned checkout of COMMIT [7c6bdf6];
# PY [the repository's .venv/bin/python] a python with this project's dependencies installed.
set -euo pipefail
repo=$(cd "$(dirname "$0")/.." && pwd)
LONGRUNS=${LONGRUNS:-/work/longruns}
WORKTREE=${WORKTREE:-/work/lr-paper}
COMMIT=${COMMIT:-7c6bdf6}
PY=${PY:-$repo/.venv/bin/python}
seed0=$LONGRUNS/paper/seed0-3e6
seeds12=$LONGRUNS/paper/seeds12-1e6
logs=$LONGRUNS/logs

usage() { echo "usage: bash experiments/paper_budget.sh start|resume|status" >&2; exit 2; }
[ $# -eq 1 ] || usage

launch() {  # launch LOG ARGS...: one run in the background, niced, importing the worktree's package
  local log=$1; shift
  (cd "$WORKTREE" && PYTHONPATH="$WORKTREE" nohup chrt -i 0 nice -n 19 "$PY" -m ttd3_jax.train "$@" \
    --compile-cache "$LONGRUNS/xla-paper" >> "$log" 2>&1 &)
}

case $1 in
  start)
    for d in "$seed0" "$seeds12"; do
      [ ! -e "$d" ] || { echo "paper_budget.sh start: $d exists; use resume" >&2; exit 1; }
    done
    [ -d "$WORKTREE" ] || git -C "$repo" worktree add --detach "$WORKTREE" "$COMMIT"
    [ "$(git -C "$WORKTREE" rev-parse --short=7 HEAD)" = "${COMMIT:0:7}" ] \
      || { echo "paper_budget.sh: $WORKTREE is not at $COMMIT" >&2; exit 1; }
    mkdir -p "$logs"
    launch "$logs/paper-seed0.log" --preset paper --seed 0 --num-seeds 1 \
      --total-transitions 3000000 --epochs 30 --out "$seed0"
    launch "$logs/paper-seeds12.log" --preset paper --seed 1 --num-seeds 2 \
      --total-transitions 1000000 --epochs 10 --out "$seeds12"
    ;;
  resume)
    for d in "$seed0" "$seeds12"; do
      [ -d "$d" ] || { echo "paper_budget.sh resume: no run directory $d; use start" >&2; exit 1; }
    done
    launch "$logs/paper-seed0.log" --resume "$seed0"
    launch "$logs/paper-seeds12.log" --resume "$seeds12"
    ;;
  status)
    for log in "$logs/paper-seed0.log" "$logs/paper-seeds12.log"; do
      echo "$log: $(grep -E 'epoch|compiled|resum' "$log" | tail -n 1)"
    done
    ;;
  *) usage ;;
esac
