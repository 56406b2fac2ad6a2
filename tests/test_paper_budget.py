"""The paper-budget runs' report (experiments/paper_budget.py) and launcher (paper_budget.sh),
on the committed unfinished runs and on refusals that start nothing."""

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


def test_report_labels_unfinished_runs_with_their_transitions(tmp_path):
    run_dirs = sorted(os.path.join(RUNS, d) for d in os.listdir(RUNS))
    assert pb.main([*run_dirs, "--out", str(tmp_path), "--machine", "test"]) == 0
    rows = [r for d in run_dirs for r in pb.run_rows(d)]
    table = (tmp_path / "table.md").read_text()
    for r in rows:  # no eval.json is committed: every seed reads "unfinished at N of budget"
        assert not r["finished"]
        assert f"unfinished at {r['transitions']:,} of {r['budget']:,}" in table
        assert r["transitions"] < r["budget"]
    assert {r["seed"] for r in rows} == {0, 1, 2}
    curves = (tmp_path / "curves.csv").read_text().splitlines()
    assert len(curves) == 1 + sum(len(r["curve"]) for r in rows)
    assert (tmp_path / "curves.png").stat().st_size > 0


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
