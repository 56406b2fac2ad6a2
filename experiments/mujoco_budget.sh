#!/bin/bash
# Claim 4's MuJoCo comparison (T-TD3 vs TD3, 4 tasks, 3 seeds vmapped, 300k env steps each)
# regenerated in the background: one process per algorithm over the four tasks, each at the idle
# scheduling class (chrt -i 0: it takes only CPU that nothing else wants) and nice 19, from a
# pinned git worktree so that later commits never change a run in flight.  Checkpointed after
# every evaluation; experiments/mujoco_compare.py skips a finished task and resumes the others.
#
#   bash experiments/mujoco_budget.sh start    # new runs (refuses if the output folder exists)
#   bash experiments/mujoco_budget.sh resume   # each from its newest checkpoint
#   bash experiments/mujoco_budget.sh status   # the last progress line of each log
#   bash experiments/mujoco_budget.sh report   # rebuild the tables and figure in the output folder
#   bash experiments/mujoco_budget.sh collect  # copy each task both algorithms finished into
#                                              # results/mujoco (replacing that task's older runs)
#                                              # and rebuild results/mujoco's tables and figure
#
# Environment (defaults in brackets): TASKS [ant walker2d inverted_double_pendulum hopper] the
# tasks start and resume train, in order (ant took 2.5 h of one idle core per algorithm on the
# AVX-512 EPYC; on a new machine, leave out those results/mujoco holds from these runs); LONGRUNS
# [/work/longruns] holds the output folder (LONGRUNS/mujoco, copied into results/mujoco by
# collect), logs and the compilation cache;
# WORKTREE [/work/lr-mujoco] the pinned checkout of COMMIT [7c6bdf6]; PY [the repository's
# .venv/bin/python] a python with this project's dependencies installed.
set -euo pipefail
repo=$(cd "$(dirname "$0")/.." && pwd)
LONGRUNS=${LONGRUNS:-/work/longruns}
WORKTREE=${WORKTREE:-/work/lr-mujoco}
COMMIT=${COMMIT:-7c6bdf6}
PY=${PY:-$repo/.venv/bin/python}
out=$LONGRUNS/mujoco
logs=$LONGRUNS/logs
ALL_TASKS="ant walker2d inverted_double_pendulum hopper"
TASKS=${TASKS:-$ALL_TASKS}
budget=(--steps 300000 --warmup 25000 --eval-every 5000 --checkpoint-every 1 --out "$out"
        --compile-cache "$LONGRUNS/xla-mujoco")
# shellcheck disable=SC2206  # the task lists are split into words on purpose
args=(--tasks $TASKS "${budget[@]}")
# shellcheck disable=SC2206
report_args=(--tasks $ALL_TASKS "${budget[@]}")

usage() { echo "usage: bash experiments/mujoco_budget.sh start|resume|status|report|collect" >&2; exit 2; }
[ $# -eq 1 ] || usage

launch() {  # launch ALGO: one algorithm's four tasks in the background, importing the worktree's package
  (cd "$WORKTREE" && PYTHONPATH="$WORKTREE" nohup chrt -i 0 nice -n 19 "$PY" experiments/mujoco_compare.py \
    --algos "$1" "${args[@]}" >> "$logs/mujoco-$1.log" 2>&1 &)
}

case $1 in
  start|resume)
    if [ "$1" = start ]; then
      [ ! -e "$out" ] || { echo "mujoco_budget.sh start: $out exists; use resume" >&2; exit 1; }
      [ -d "$WORKTREE" ] || git -C "$repo" worktree add --detach "$WORKTREE" "$COMMIT"
    else
      [ -d "$out" ] || { echo "mujoco_budget.sh resume: no output folder $out; use start" >&2; exit 1; }
    fi
    [ "$(git -C "$WORKTREE" rev-parse --short=7 HEAD)" = "${COMMIT:0:7}" ] \
      || { echo "mujoco_budget.sh: $WORKTREE is not at $COMMIT" >&2; exit 1; }
    mkdir -p "$logs" "$out"
    launch ttd3
    launch td3
    ;;
  status)
    for log in "$logs/mujoco-ttd3.log" "$logs/mujoco-td3.log"; do
      echo "$log: $(grep -E 'epoch|compiled|resum|step' "$log" | tail -n 1)"
    done
    ;;
  report) (cd "$WORKTREE" && PYTHONPATH="$WORKTREE" "$PY" experiments/mujoco_compare.py "${report_args[@]}" --report-only) ;;
  collect)
    dest=$repo/results/mujoco
    for task in $ALL_TASKS; do
      runs=()
      for algo in ttd3 td3; do
        d=$(ls -d "$out/runs/$task-$algo"/*/ 2>/dev/null | tail -n 1 || true)
        [ -n "$d" ] && [ -f "$d/eval.json" ] && runs+=("${d%/}")
      done
      [ ${#runs[@]} -eq 2 ] || { echo "$task: not finished by both algorithms; left as it is"; continue; }
      for d in "${runs[@]}"; do
        name=$(basename "$(dirname "$d")")  # e.g. ant-ttd3
        keep=$dest/runs/$name/$(basename "$d")
        rm -rf "$dest/runs/$name" && mkdir -p "$keep"
        cp "$d"/config.json "$d"/metrics.csv "$d"/eval.json "$keep"/
        for f in learning_curve.png launches.jsonl; do [ ! -f "$d/$f" ] || cp "$d/$f" "$keep"/; done
        (cd "$repo" && "$PY" experiments/current_format.py "$keep/config.json")  # the pinned commit's format
        "$PY" - "$keep/eval.json" "${keep#"$repo"/}" <<'PY'
import json, sys
path, run_dir = sys.argv[1:]
d = json.load(open(path))
d["run_dir"] = run_dir  # where the run's files are committed, not where it ran
json.dump(d, open(path, "w"), indent=2)
PY
        echo "$task: $d -> ${keep#"$repo"/}"
      done
    done
    (cd "$repo" && "$PY" experiments/mujoco_compare.py "${report_args[@]}" --out "$dest" --report-only)
    ;;
  *) usage ;;
esac
