"""experiments/robust_table.py (issue 37's table): its argument errors, the provenance check of a
saved NMPC robustness file, the target logic on hand numbers, and (slow) a tiny robust-like
run through the whole script.  Everything runs on CPU."""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import os

import pytest
from experiment_scripts import experiment
from test_evaluate import fake_run_dir

from ttd3_jax.control.robustness import ROBUSTNESS_CONDITIONS, ROBUSTNESS_DESCRIPTIONS
from ttd3_jax.run import spec as sp
from ttd3_jax.run.loop import run

HERE = os.path.dirname(os.path.abspath(__file__))
NMPC_JSON = os.path.join(HERE, "..", "results", "robustness", "nmpc.json")


def _script():
    return experiment("robust_table")


def nmpc_file(n: int) -> dict:
    """The committed NMPC robustness result (LOS-RT seeds 1..20) relabelled as seeds 1..n."""
    with open(NMPC_JSON) as fh:
        d = json.load(fh)
    for r in d["robustness"]["nmpc"].values():
        r["los_rt"]["seeds"] = list(range(1, n + 1))
    return d


# --------------------------------------------------------------------------- the targets


def test_verdict_counts_the_seeds_that_meet_a_target_and_states_the_worst_miss():
    rt = _script()
    v = rt.verdict([4.0, 5.0, 6.0], 5.0, ref=5.0)
    assert v["met"] == [True, True, False] and (v["k"], v["n"]) == (2, 3)
    assert v["worst_ratio"] == pytest.approx(1.2) and v["text"] == "2/3; worst 1.20× NMPC"
    assert rt.verdict([1.0, 2.0, 3.0], 5.0, ref=5.0)["text"] == "3/3"  # met: no ratio
    # steady state: at most 2x the NMPC's, the miss stated as the ratio to the NMPC itself
    steady = rt.verdict([1.0, 2.5, 3.0], 2 * 1.0, ref=1.0, note="limit 2×")
    assert steady["text"] == "1/3; worst 3.00× NMPC (limit 2×)"
    # an absolute limit (the step's overshoot): the worst value, not a ratio
    over = rt.verdict([3.0, 12.5, 9.0], 10.0, unit=" %", note="limit 10 %")
    assert over["text"] == "2/3; worst 12.5 % (limit 10 %)" and "worst_ratio" not in over
    # against the paper's figures
    assert rt.verdict([20.0, 30.0], 25.99, ref=25.99, ref_name="paper")["text"] == "1/2; worst 1.15× paper"


def test_verdict_a_crash_misses_even_below_the_limit_and_nan_never_meets():
    rt = _script()
    v = rt.verdict([1.0, 1.0, 1.0], 5.0, crashes=[0, 1, 0], ref=5.0)
    assert v["met"] == [True, False, True] and v["text"] == "2/3; worst 0.20× NMPC; 1 seed crashed"
    # LOS-RT rows count crashed tracks: more than the NMPC's is a miss, as many is not
    los = rt.verdict([100.0, 100.0, 900.0], 300.0, crashes=[2, 3, 5], ref_crashes=2, ref=300.0)
    assert los["met"] == [True, False, False] and los["crashed"] == 2
    assert los["text"] == "1/3; worst 3.00× NMPC; 2 seeds crashed more often than NMPC"
    nan = rt.verdict([math.nan, 1.0], 5.0, ref=5.0)
    assert nan["met"] == [False, True] and nan["worst_ratio"] == math.inf and "∞× NMPC" in nan["text"]
    # an NMPC that failed (non-finite) bounds nothing; the policy's crashes still count
    assert rt.verdict([1e6, 2.0], math.inf, crashes=[0, 1], ref=math.inf)["met"] == [True, False]


# --------------------------------------------------------------------------- the saved NMPC


def test_the_committed_nmpc_file_is_accepted_for_its_own_seeds_only():
    rt = _script()
    with open(NMPC_JSON) as fh:
        d = json.load(fh)
    assert rt.nmpc_file_mismatch(d, 20) is None
    assert rt.nmpc_file_mismatch(d, 5) == "its LOS-RT seeds are 1..20, not 1..5 (--robustness-seeds 5)"


def test_the_nmpc_file_check_refuses_another_condition_set_controller_or_config():
    rt = _script()
    base = nmpc_file(1)
    assert rt.nmpc_file_mismatch(base, 1) is None

    def changed(edit):
        d = copy.deepcopy(base)
        edit(d)
        return rt.nmpc_file_mismatch(d, 1)

    def drop(d):  # the old condition set: without pos_bias2cm
        del d["robustness_conditions"]["pos_bias2cm"], d["robustness"]["nmpc"]["pos_bias2cm"]

    assert "not today's" in changed(drop)
    renamed = lambda d: d["robustness_conditions"].update({"mass+30": "vehicle mass +20%"})  # noqa: E731
    assert changed(renamed) == (
        "its condition(s) ['mass+30'] are described differently from today's (another perturbation)"
    )
    assert "not every condition" in changed(lambda d: d["robustness"]["nmpc"].pop("wind1.0"))
    assert "controller 'geometric'" in changed(lambda d: d.update(controller="geometric"))
    assert "options" in changed(lambda d: d.update(options={"horizon": 10}))
    assert "preset 'practical'" in changed(lambda d: d.update(preset="practical"))
    heavy = lambda d: d["env_config"]["vehicle"]["quad"].update(mass=1.8)  # noqa: E731
    assert changed(heavy) == "its env config differs from the paper preset's in vehicle.quad.mass"
    assert "holds no robustness" in changed(lambda d: d.pop("robustness"))
    d = nmpc_file(3)
    d["robustness"]["nmpc"]["wind0.5"]["los_rt"]["seeds"] = [1, 2, 4]
    assert rt.nmpc_file_mismatch(d, 3) == "its LOS-RT seeds are 1..4, not 1..3 (--robustness-seeds 3)"


def test_a_cf2_nmpc_file_stands_only_for_a_cf2_run():
    """A saved NMPC robustness file of the cf2 vehicle (evaluate --vehicle cf2) is checked
    against the paper preset with the cf2 vehicle, and a paper file is no cf2 file."""
    rt = _script()
    d = nmpc_file(1)
    d["vehicle"] = "cf2"
    d["env_config"] = json.loads(json.dumps(rt.json_safe(dataclasses.asdict(rt.nmpc_config("cf2")))))
    assert rt.nmpc_file_mismatch(d, 1, "cf2") is None and rt.nmpc_file_mismatch(d, 1, None) is None
    assert "not the paper preset's nominal paper vehicle" in rt.nmpc_file_mismatch(d, 1, "paper")
    assert "not the paper preset's nominal cf2 vehicle" in rt.nmpc_file_mismatch(nmpc_file(1), 1, "cf2")
    d["env_config"]["vehicle"]["quad"]["mass"] = 0.04
    assert rt.nmpc_file_mismatch(d, 1, None) == (
        "its env config differs from the paper preset's (cf2 vehicle) in vehicle.quad.mass"
    )
    assert rt.reference_preset(sp.preset("cf2")) == "cf2" and rt.robust_differences(sp.preset("cf2")) == []
    assert rt.reference_preset(sp.preset("robust")) == "robust"


# --------------------------------------------------------------------------- arguments


def test_bad_arguments_are_refused_with_one_line_before_anything_compiles(tmp_path, capsys):
    rt = _script()
    run_dir = fake_run_dir(tmp_path / "run")  # no best/: not a run with selected policies
    out = str(tmp_path / "out")
    wrong = tmp_path / "nmpc5.json"
    wrong.write_text(json.dumps(nmpc_file(5)))
    (tmp_path / "bad.json").write_text("{")
    (tmp_path / "file").write_text("")
    brax = tmp_path / "brax"
    brax.mkdir()
    (brax / "config.json").write_text(json.dumps(sp.to_dict(sp.preset("mujoco"))))
    cases = {
        (str(tmp_path / "nothing"),): "not a ttd3_jax run directory",
        (run_dir,): "no selected policy for seed(s) [0]",
        (str(brax),): "'hopper' run; only quadrotor runs",
        (run_dir, "--robustness-seeds", "0"): "--robustness-seeds must be >= 1, got 0",
        (run_dir, "--nmpc-robustness", str(wrong)): "its LOS-RT seeds are 1..5, not 1..20",
        (run_dir, "--nmpc-robustness", str(tmp_path / "bad.json")): "is not valid JSON",
        (run_dir, "--nmpc-robustness", str(tmp_path / "none.json")): "cannot read it",
        (run_dir, "--out", str(tmp_path / "file")): "--out",
        (str(brax), "--fast-run", run_dir): "ROBUST_RUN",
    }
    for argv, message in cases.items():
        argv = [*argv, "--out", out] if "--out" not in argv else list(argv)
        with pytest.raises(SystemExit) as e:
            rt.main(argv)
        assert e.value.code == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert message in err[-1] and "Traceback" not in "".join(err), (argv, err)
    assert not os.path.exists(out)


def test_the_readme_command_names_the_runs_not_their_paths():
    rt = _script()
    assert rt.shown_words(["/r", "--fast-run", "/r", "--out", "/o"]) == [
        "ROBUST_RUN", "--fast-run", "FAST_RUN", "--out", "/o"
    ]  # fmt: skip
    assert rt.shown_words(["--out", "/r", "--fast-run=/f", "/r"]) == [
        "--out", "/r", "--fast-run=FAST_RUN", "ROBUST_RUN"
    ]  # fmt: skip


def test_a_non_robust_run_is_named_so_in_the_header():
    rt = _script()
    assert rt.robust_differences(sp.preset("robust")) == []
    diff = rt.robust_differences(sp.preset("fast"))
    assert "mass" in diff and "obs_memory" in diff and "wide_mix" in diff and "model_horizon" not in diff
    assert "model_horizon" in rt.robust_differences(sp.preset("fast_model_free"))


# --------------------------------------------------------------------------- end to end


@pytest.mark.slow
def test_a_tiny_robust_run_through_the_script(tmp_path, capsys):
    rt = _script()
    spec = sp.preset("robust", num_envs=16, total_transitions=16 * 40, warmup_transitions=16 * 8,
                     buffer_size=16 * 64, batch_size=64, updates_per_step=2, epochs=2, hidden=(32, 32),
                     model_horizon=2, num_seeds=2)  # fmt: skip
    run_dir = run(spec, out=str(tmp_path / "runs"), verbose=False)["run_dir"]
    nmpc = tmp_path / "nmpc.json"
    nmpc.write_text(json.dumps(nmpc_file(1)))
    out = str(tmp_path / "out")
    argv = [run_dir, "--fast-run", run_dir, "--nmpc-robustness", str(nmpc), "--robustness-seeds", "1"]
    assert rt.main([*argv, "--out", out]) == 0
    printed = capsys.readouterr().out
    assert "It has 2 seed(s), not the 3" in printed and "Not the `robust` preset" not in printed
    with open(os.path.join(out, "robust_table.json")) as fh:
        d = json.load(fh)
    labels = ["robust seed 0", "robust seed 1", "fast seed 0", "fast seed 1", "NMPC"]
    assert list(d["results"]) == labels and d["judged"] == labels[:2] and d["los_seeds"] == [1]
    # the same policies as robust and as fast columns: the same numbers
    for a, b in (("robust seed 0", "fast seed 0"), ("robust seed 1", "fast seed 1")):
        assert d["results"][a] == d["results"][b]
    nmpc = d["results"]["NMPC"]
    assert nmpc["control_hz"] == 1000 and d["results"]["robust seed 0"]["control_hz"] == 100
    assert nmpc["robustness"] == nmpc_file(1)["robustness"]["nmpc"]  # the saved rows, as read
    assert set(d["results"]["robust seed 1"]["robustness"]) == set(ROBUSTNESS_CONDITIONS)
    rows = d["targets"]
    assert len(rows) == 2 + 7 * 2 + 1 + 2 * len(ROBUSTNESS_CONDITIONS)
    for name, t in rows.items():
        assert t["n"] == 2 and 0 <= t["k"] <= 2 and t["text"].startswith(f"{t['k']}/2"), name
        assert set(t["values"]) == set(labels), name
    nominal = rows["nominal: LOS-RT 1..1 mean Σ‖e‖ [m]"]
    assert nominal["values"]["NMPC"] == pytest.approx(238.492, abs=1e-3)
    text = open(os.path.join(out, "README.md")).read()
    assert "`python experiments/robust_table.py ROBUST_RUN --fast-run FAST_RUN --nmpc-robustness" in text
    table = [ln for ln in text.splitlines() if ln.startswith("| ")]
    assert table[0] == "| row | " + " | ".join(labels) + " | target |" and len(table) == 2 + len(rows)
    assert all(ln.count(" | ") == len(labels) + 1 for ln in table[2:])
    assert all(f"- {k}: {v}" in text for k, v in ROBUSTNESS_DESCRIPTIONS.items())
