#!/bin/bash
# The `paper` preset at the paper's budget (issue 35): seed 0 to 3e6 transitions, seeds 1 and 2
# to 1e6, each its own process in the background at the idle scheduling class (chrt -i 0: it
# takes only CPU that nothing else wants) and nice 19, from a pinned git worktree so that later
# commits never change a run in flight.  Reported by experiments/paper_budget.py.
#
#   bash experiments/paper_budget.sh start [RUN ...]    # new runs (refuses if a run directory exists)
#   bash experiments/paper_budget.sh resume [RUN ...]   # each from its newest checkpoint
#   bash experiments/paper_budget.sh status             # the last progress line of each log
#   bash experiments/paper_budget.sh collect            # copy the runs' files into results/paper_budget
#                                                       # and rebuild its table and curves
#
# RUN is seed0 (3e6 transitions, about 7 h of one idle core), seed1 or seed2 (1e6, about 2.5 h
# each; both estimated from benchmarks/trainer_throughput.py's paper case); without one, all
# three.  Seeds 1 and 2 each fit in one session's three hours when each has a core to itself,
# so on a new machine start them first and seed 0 after.
#
# Environment (defaults in brackets): LONGRUNS [/work/longruns] holds the run directories, logs
# and the compilation cache; WORKTREE [/work/lr-paper] the pinned checkout of COMMIT [4df86f0];
# PY [the repository's .venv/bin/python] a python with this project's dependencies installed.
set -euo pipefail
repo=$(cd "$(dirname "$0")/.." && pwd)
LONGRUNS=${LONGRUNS:-/work/longruns}
WORKTREE=${WORKTREE:-/work/lr-paper}
COMMIT=${COMMIT:-4df86f0}
PY=${PY:-$repo/.venv/bin/python}
logs=$LONGRUNS/logs
ALL=(seed0 seed1 seed2)

usage() { echo "usage: bash experiments/paper_budget.sh start|resume [seed0|seed1|seed2 ...] | status | collect" >&2; exit 2; }
[ $# -ge 1 ] || usage
cmd=$1; shift
runs=("$@"); [ ${#runs[@]} -gt 0 ] || runs=("${ALL[@]}")

dir_of() {  # dir_of RUN: the run directory's name
  case $1 in
    seed0) echo seed0-3e6 ;;
    seed1|seed2) echo "$1-1e6" ;;
    *) echo "paper_budget.sh: unknown run '$1'; allowed: ${ALL[*]}" >&2; exit 2 ;;
  esac
}

launch() {  # launch RUN ARGS...: one run in the background, niced, importing the worktree's package
  local log=$logs/paper-$1.log; shift
  (cd "$WORKTREE" && PYTHONPATH="$WORKTREE" nohup chrt -i 0 nice -n 19 "$PY" -m ttd3_jax.train "$@" \
    --compile-cache "$LONGRUNS/xla-paper" >> "$log" 2>&1 &)
}

case $cmd in
  start)
    for r in "${runs[@]}"; do
      d=$LONGRUNS/paper/$(dir_of "$r")
      [ ! -e "$d" ] || { echo "paper_budget.sh start: $d exists; use resume" >&2; exit 1; }
    done
    [ -d "$WORKTREE" ] || git -C "$repo" worktree add --detach "$WORKTREE" "$COMMIT"
    [ "$(git -C "$WORKTREE" rev-parse --short=7 HEAD)" = "${COMMIT:0:7}" ] \
      || { echo "paper_budget.sh: $WORKTREE is not at $COMMIT" >&2; exit 1; }
    mkdir -p "$logs" "$LONGRUNS/paper"
    for r in "${runs[@]}"; do
      if [ "$r" = seed0 ]; then budget=(--total-transitions 3000000 --epochs 30); else budget=(--total-transitions 1000000 --epochs 10); fi
      launch "$r" --preset paper --seed "${r#seed}" --num-seeds 1 "${budget[@]}" --out "$LONGRUNS/paper/$(dir_of "$r")"
    done
    ;;
  resume)
    for r in "${runs[@]}"; do
      d=$LONGRUNS/paper/$(dir_of "$r")
      [ -d "$d" ] || { echo "paper_budget.sh resume: no run directory $d; use start" >&2; exit 1; }
    done
    for r in "${runs[@]}"; do launch "$r" --resume "$LONGRUNS/paper/$(dir_of "$r")"; done
    ;;
  status)
    for r in "${ALL[@]}"; do
      log=$logs/paper-$r.log
      [ -f "$log" ] && echo "$log: $(grep -E 'epoch|compiled|resum' "$log" | tail -n 1)" || echo "$log: not started"
    done
    ;;
  collect)  # each finished run replaces its committed files; the runs still in flight are left out
    dest=$repo/results/paper_budget
    for r in "${ALL[@]}"; do
      d=$LONGRUNS/paper/$(dir_of "$r")
      [ -f "$d/eval.json" ] || { echo "$r: not finished; left as it is"; continue; }
      keep=$dest/runs/$(dir_of "$r")
      rm -rf "$keep" && mkdir -p "$keep"
      cp "$d"/config.json "$d"/metrics.csv "$d"/state.json "$d"/eval.json "$keep"/
      [ ! -f "$d/launches.jsonl" ] || cp "$d/launches.jsonl" "$keep"/  # written from a898951 on
      (cd "$repo" && "$PY" experiments/current_format.py "$keep/config.json")  # the pinned commit's format
      echo "$r: $d -> ${keep#"$repo"/}"
    done
    if [ -d "$dest/runs/seed1-1e6" ] && [ -d "$dest/runs/seed2-1e6" ]; then
      rm -rf "$dest/runs/seeds12-1e6"  # the earlier layout: seeds 1 and 2 vmapped in one run
    fi
    (cd "$repo" && "$PY" experiments/paper_budget.py "$dest"/runs/* --out "$dest" \
      --machine "${MACHINE:-$(uname -m) CPU, $(nproc) cores}")
    ;;
  *) usage ;;
esac
