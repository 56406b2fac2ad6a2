"""Data checks of committed results (results/): the files load and agree with each other and
with what the docs say of them.  The behaviour of the code is tested elsewhere."""

from __future__ import annotations

import csv
import os

from experiment_scripts import experiment

HERE = os.path.dirname(os.path.abspath(__file__))
RESULTS = os.path.join(HERE, "..", "results")


def test_committed_mujoco_runs_load_and_the_summary_states_their_budgets():
    """results/mujoco/runs/*/*/config.json are run specs that load; every finished run's budget
    (from its own config) is the one summary.csv and summary.md report, and each is labelled
    by what it is against the 1M-step protocol."""
    mc = experiment("mujoco_compare")
    out = os.path.join(RESULTS, "mujoco")
    b = {(r["task"], r["algo"]): r for r in mc.budgets(out)}
    assert set(b) == {(t, a) for t in mc.TASKS for a in mc.ALGOS}
    with open(os.path.join(out, "summary.csv")) as fh:
        summary = {(r["task"], r["algo"]): r for r in csv.DictReader(fh)}
    text = open(os.path.join(out, "summary.md")).read()
    for key, r in b.items():
        assert r["finished"], key
        assert int(summary[key]["last_step"]) == r["steps"], key
        assert (r["steps"] - r["warmup"]) % r["eval_every"] == 0, key  # whole evaluation intervals
        assert f"| {key[0]} | {mc.LABEL[key[1]]} | {r['seeds']} | {r['steps']} |" in text, key
        assert (mc.protocol_label(r) == "yes") == r["protocol"], key
        assert (r["num_envs"], r["updates_per_step"]) == (1, 1), key  # the protocol's UTD 1, one env
