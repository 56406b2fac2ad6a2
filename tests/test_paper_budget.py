"""The paper-budget runs' report (experiments/paper_budget.py) and launcher (paper_budget.sh),
on the committed runs and on refusals that start nothing."""

from __future__ import annotations

import os
import shutil
import subprocess

import pytest
from experiment_scripts import experiment

ROOT = os.path.join(os.path.dirname(__file__), "..")
RUNS = os.path.join(ROOT, "results", "paper_budget", "runs")
LAUNCHER = os.path.join(ROOT, "experiments", "paper_budget.sh")

pb = experiment("paper_budget")


def test_report_labels_each_run_finished_or_unfinished_at_its_transitions(tmp_path):
    run_dirs = sorted(os.path.join(RUNS, d) for d in os.listdir(RUNS))
    assert pb.main([*run_dirs, "--out", str(tmp_path), "--machine", "test"]) == 0
    rows = [r for d in run_dirs for r in pb.run_rows(d)]
    table = (tmp_path / "table.md").read_text()
    for r in rows:  # a run is finished iff its eval.json is committed
        assert r["finished"] == os.path.exists(os.path.join(RUNS, r["run"], "eval.json"))
        spec = pb.rundir.load_spec(os.path.join(RUNS, r["run"]))
        if r["finished"]:  # the budget rounded down to whole epochs
            assert r["transitions"] == spec.train.transitions_run > 0.99 * r["budget"]
        else:
            assert f"unfinished at {r['transitions']:,} of {r['budget']:,}" in table
            assert r["transitions"] < r["budget"]
        assert r["selected"] is not None and 1 <= r["selected"]["epoch"] <= len(r["curve"])
        longest = spec.task.episode_steps
        assert len(r["mean_episode"]) == len(r["curve"])
        assert all(0 < n <= longest for n in r["mean_episode"])  # a mean over episodes of ≤ 3000 steps
    assert {r["seed"] for r in rows} == {0, 1, 2}
    curves = (tmp_path / "curves.csv").read_text().splitlines()
    assert len(curves) == 1 + sum(len(r["curve"]) for r in rows)
    assert (tmp_path / "curves.png").stat().st_size > 0


def test_selection_from_metrics_matches_the_trainers_record(tmp_path):
    """An unfinished run's selected epoch (metrics.csv) follows the rule the trainer recorded in
    eval.json for the finished runs: each seed's lowest validation error."""
    finished = [d for d in sorted(os.listdir(RUNS)) if os.path.exists(os.path.join(RUNS, d, "eval.json"))]
    if not finished:
        pytest.skip("no finished run committed")
    for d in finished:
        copy = tmp_path / d
        shutil.copytree(os.path.join(RUNS, d), copy)
        os.remove(copy / "eval.json")
        recorded = pb.selected_epochs(os.path.join(RUNS, d), pb.rundir.read_metrics(os.path.join(RUNS, d)))
        derived = pb.selected_epochs(str(copy), pb.rundir.read_metrics(str(copy)))
        assert recorded.keys() == derived.keys()
        for seed, rec in recorded.items():
            assert derived[seed]["epoch"] == rec["epoch"]
            for k in ("val_tracking_error", "spiral_tracking_error", "los_tracking_error"):
                assert derived[seed][k] == pytest.approx(rec[k], rel=1e-6)


def test_report_refuses_a_directory_that_is_not_a_run(tmp_path, capsys):
    assert pb.main([str(tmp_path), "--out", str(tmp_path / "out")]) == 2
    assert "not a run directory" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


@pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")
@pytest.mark.parametrize(
    "args, make_dirs, rc, message",
    [
        ([], False, 2, "usage"),
        (["go"], False, 2, "usage"),
        (["resume"], False, 1, "no run directory"),
        (["start"], True, 1, "exists; use resume"),
    ],
)
def test_launcher_refuses_before_starting_anything(tmp_path, args, make_dirs, rc, message):
    if make_dirs:
        (tmp_path / "paper" / "seed0-3e6").mkdir(parents=True)
    env = dict(os.environ, LONGRUNS=str(tmp_path), WORKTREE=str(tmp_path / "wt"), PY="false")
    p = subprocess.run(["bash", LAUNCHER, *args], env=env, capture_output=True, text=True, timeout=30)
    assert p.returncode == rc and message in p.stderr
    assert not (tmp_path / "wt").exists() and not (tmp_path / "logs").exists()
