"""experiments/mujoco_compare.py without training (MJX compiles take minutes on a CPU): the
configs and their errors, the summary statistics, the per-run budgets and the README, on
synthetic run directories."""

from __future__ import annotations

import csv
import json
import math
import os

import numpy as np
import pytest
from experiment_scripts import experiment

from ttd3_jax.run import spec as sp

HERE = os.path.dirname(os.path.abspath(__file__))
mc = experiment("mujoco_compare")


def test_task_config_is_the_mujoco_preset_resized():
    a = mc.parse(["--steps", "40000", "--warmup", "5000", "--eval-every", "2500", "--tasks", "hopper"])
    c = mc.task_config("hopper", "td3", a)
    tc = c.train
    assert (c.env, c.algo, tc.num_envs, tc.updates_per_step, c.num_seeds) == ("hopper", "td3", 1, 1, 3)
    assert tc.epochs == 14 and tc.steps_per_epoch == 2500 and tc.warmup_transitions == 5000
    assert (c.brax.backend, c.brax.eval_episodes) == ("mjx", 10)
    t = mc.task_config("hopper", "ttd3", a)
    assert t.algo == "ttd3" and t.hp == c.hp and t.train.hidden == tc.hidden == (256, 256)


@pytest.mark.parametrize(
    "argv, match",
    [
        (["--steps", "4000", "--warmup", "5000"], "at least one evaluation interval"),
        (["--eval-every", "1001", "--num-envs", "2"], "multiple of --num-envs"),
    ],
)
def test_task_config_errors_name_the_option(argv, match):
    with pytest.raises(ValueError, match=match):
        mc.task_config("hopper", "ttd3", mc.parse(argv))


@pytest.mark.parametrize("argv", [["--seeds", "0"], ["--warmup", "10"], ["--tasks", "humanoid"]])
def test_parse_rejects_bad_values(argv, capsys):
    with pytest.raises(SystemExit):
        mc.parse(argv)
    assert "error" in capsys.readouterr().err


def rows_for(task, algo, finals, steps=(5000, 10000, 15000)):
    return [
        dict(task=task, algo=algo, seed=s, step=t, eval_return=f * t / steps[-1])
        for s, f in enumerate(finals)
        for t in steps
    ]


def test_summary_statistics():
    rows = rows_for("hopper", "td3", [100.0, 200.0]) + rows_for("hopper", "ttd3", [300.0, 300.0])
    by = {r["algo"]: r for r in mc.summarize(rows)}
    assert by["td3"]["final_mean"] == pytest.approx(150.0) and by["td3"]["final_std"] == pytest.approx(50.0)
    # seed-mean curves: td3 50, 100, 150; ttd3 100, 200, 300 at 5k, 10k, 15k steps
    assert by["td3"]["auc"] == pytest.approx(100.0) and by["ttd3"]["auc"] == pytest.approx(200.0)
    # 80 % of TD3's final (120): TD3 first reaches it at 15k, T-TD3 at 10k
    assert by["td3"]["steps_to_80pct_td3"] == 15000 and by["ttd3"]["steps_to_80pct_td3"] == 10000
    lines = mc.reading(mc.summarize(rows))
    assert len(lines) == 1 and "T-TD3 ahead" in lines[0] and "slightly worse" in lines[0]
    assert math.isnan(mc.steps_to(np.array([1, 2]), np.array([0.0, 1.0]), 5.0))


def test_paired_test_over_seeds():
    rows = rows_for("hopper", "td3", [100.0, 200.0, 150.0]) + rows_for(
        "hopper", "ttd3", [130.0, 190.0, 190.0]
    )
    pr = mc.paired(rows, "hopper")
    # per-seed final differences +30, -10, +40: mean 20, T-TD3 ahead in 2 of 3
    assert pr["seeds"] == 3 and pr["final_diff"] == pytest.approx(20.0) and pr["final_wins"] == 2
    from scipy import stats

    assert pr["final_p"] == pytest.approx(stats.ttest_rel([130, 190, 190], [100, 200, 150]).pvalue)
    line = mc.reading(mc.summarize(rows), rows)[0]
    assert "Paired over 3 seeds: final +20.0 (T-TD3 ahead in 2/3" in line
    assert mc.paired(rows_for("hopper", "td3", [1.0]), "hopper") is None
    # TD3's seed 0 never reaches 80 % of TD3's final mean (120): no difference, no test
    assert math.isnan(pr["steps80_diff"]) and math.isnan(pr["steps80_p"])
    assert "steps to 80 % of TD3's final not reached by every seed." in line


def test_paired_steps_to_80_percent_of_td3s_final():
    rows = rows_for("hopper", "td3", [150.0] * 3) + rows_for("hopper", "ttd3", [300.0, 150.0, 360.0])
    pr = mc.paired(rows, "hopper")
    # level 120: TD3's seeds reach it at 15k; T-TD3's at 10k, 15k and 5k
    assert pr["level"] == pytest.approx(120.0)
    assert pr["steps80_diff"] == pytest.approx(-5000.0) and pr["steps80_wins"] == 2
    from scipy import stats

    assert pr["steps80_p"] == pytest.approx(stats.ttest_rel([10000, 15000, 5000], [15000] * 3).pvalue)
    line = mc.reading(mc.summarize(rows), rows)[0]
    assert "steps to 80 % of TD3's final -5000 (T-TD3 sooner in 2/3" in line


def fake_run(out, task, algo, argv):
    """A run directory as the runner writes it: config.json, metrics.csv, eval.json."""
    a = mc.parse(argv)
    c = mc.task_config(task, algo, a)
    d = os.path.join(out, "runs", f"{task}-{algo}", f"{task}-{algo}-s0-20261201-000000")
    os.makedirs(d)
    with open(os.path.join(d, "config.json"), "w") as fh:
        json.dump(sp.to_dict(c), fh)
    with open(os.path.join(d, "metrics.csv"), "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["epoch", "seed", "env_steps", "eval_return"])
        for e in range(1, c.train.epochs + 1):
            for s in range(c.num_seeds):
                w.writerow([e, s, c.train.warmup_transitions + e * a.eval_every, 10.0 * e + s])
    with open(os.path.join(d, "eval.json"), "w") as fh:
        json.dump({}, fh)
    return a


def test_readme_states_each_runs_budget_and_flags_reduced_runs(tmp_path):
    out = str(tmp_path)
    small = ["--steps", "40000", "--warmup", "5000", "--eval-every", "2500", "--out", out]
    for algo in ("ttd3", "td3"):
        fake_run(out, "hopper", algo, small + ["--tasks", "hopper"])
        ant = ["--steps", "15000", "--warmup", "5000", "--out", out, "--tasks", "ant"]
        a = fake_run(out, "ant", algo, ant)
    b = {(r["task"], r["algo"]): r for r in mc.budgets(out)}
    assert b["hopper", "td3"]["steps"] == 40000 and b["hopper", "td3"]["eval_every"] == 2500
    assert b["ant", "ttd3"]["steps"] == 15000 and b["ant", "ttd3"]["eval_every"] == 5000
    assert not any(r["protocol"] for r in b.values())
    a.report_only = False
    a.device_note = "test machine"
    with open(os.path.join(out, "commands.txt"), "w") as fh:  # a note a person added, and a blank line
        fh.write("2026-12-01  python experiments/mujoco_compare.py --tasks hopper\n# resumed at 06:25\n\n")
    summary = mc.report(a, wall_s=1.0)
    assert {s["task"] for s in summary} == {"hopper", "ant"}
    text = open(os.path.join(out, "README.md")).read()
    assert "**Reduced runs, not the paper's protocol.**" in text
    assert "| hopper | TD3 | 40000 | 3 | 1 x 1 | 5000 | 2500 (10) | mjx | yes | **no: reduced** |" in text
    assert "| ant | T-TD3 | 15000 |" in text and "- device: cpu (test machine)" in text
    assert "  - 2026-12-01: `python experiments/mujoco_compare.py --tasks hopper`" in text
    assert "resumed at" not in text and "- : ``" not in text  # notes are pointed to, not listed
    assert "[commands.txt](commands.txt) also holds 1 line of notes" in text
    assert os.path.getsize(os.path.join(out, "curves.png")) > 10_000
    with open(os.path.join(out, "evals.csv")) as fh:
        assert len(list(csv.DictReader(fh))) == 2 * 3 * (14 + 2)  # algos x seeds x evaluations


def test_a_run_short_only_of_the_protocols_steps_says_its_share(tmp_path):
    out = str(tmp_path)
    argv = ["--steps", "300000", "--warmup", "25000", "--eval-every", "5000", "--out", out]
    argv += ["--tasks", "hopper"]
    fake_run(out, "hopper", "td3", argv)
    fake_run(out, "hopper", "ttd3", argv[:3] + ["20000"] + argv[4:])  # a 20k warm-up is reduced
    b = {r["algo"]: r for r in mc.budgets(out)}
    assert mc.protocol_settings(b["td3"]) and not b["td3"]["protocol"]
    assert mc.protocol_label(b["td3"]) == "**no: 30 % of its steps**"
    assert mc.protocol_label(b["ttd3"]) == "**no: reduced**"
    assert mc.protocol_label({**b["td3"], "steps": 1_000_000, "protocol": True}) == "yes"
    text = mc.budget_markdown(mc.budgets(out))
    row = "| hopper | TD3 | 300000 | 3 | 1 x 1 | 25000 | 5000 (10) | mjx | yes | **no: 30 % of its steps** |"
    assert row in text
