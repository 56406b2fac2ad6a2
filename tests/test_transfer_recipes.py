"""experiments/transfer_recipes.py without training: a seed's summary from the harness's
figures, the table, a folder made otherwise, and bad arguments."""

from __future__ import annotations

import json

import pytest
from experiment_scripts import experiment

tr = experiment("transfer_recipes")


def flight(error, own, mellinger, crashed=False):
    return {"tracking_error": error, "crashed": crashed, "own_sim_tracking_error": own,
            "mellinger_tracking_error": mellinger}  # fmt: skip


def test_a_seed_summary_reads_crashes_the_worst_ratio_and_the_mellinger_count():
    tracks = {"spiral_rt": flight(8.0, 8.0, 105.0), "circle_r0.5": flight(220.0, 110.0, 217.0),
              "los_rt_seed00": flight(700.0, 350.0, 2500.0, crashed=True)}  # fmt: skip
    s = tr.seed_summary(tracks)
    assert s["crashes"] == ["los_rt_seed00"]
    assert s["max_ratio"] == 2.0 and s["worst"] in ("los_rt_seed00", "circle_r0.5")
    assert (s["beats_mellinger"], s["tracks"]) == (2, 3)
    assert (s["own_spiral"], s["own_los"]) == (8.0, 350.0)
    row = tr.table([{"description": "d", "seeds": [s]}]).splitlines()[-1]
    assert row.startswith("| d | 0 | 8.00 | 350.00 | los_rt_seed00 | 2.00 (") and row.endswith("| 2/3 |")


def test_every_variant_is_the_preset_plus_valid_changes():
    from ttd3_jax.run import spec as sp

    for name in tr.VARIANTS:
        made = tr.made_with(name, quick=True)
        spec = tr.variant_spec(made)  # validated: a bad change raises here
        base = sp.preset(made["preset"], **made["budget"])
        assert spec.task == base.task.replace(**tr.task_changes(made))
        for field, value in made.get("train", {}).items():
            where = spec.hp if hasattr(spec.hp, field) else spec.train  # a Hyper or TrainConfig field
            assert getattr(where, field) == (tuple(value) if isinstance(value, list) else value)
    assert tr.variant_spec(tr.made_with("wide", quick=True)).train.hidden == (128, 128)
    decay = tr.variant_spec(tr.made_with("decay_lr6e-3", quick=True)).hp
    assert (decay.lr_actor, decay.lr_decay) == (6e-3, 1.0)


def test_a_folder_made_otherwise_is_refused_before_training(tmp_path):
    (tmp_path / "cf2").mkdir()
    (tmp_path / "cf2" / "flags.json").write_text(json.dumps({"preset": "robust", "task": {}, "budget": {}}))
    with pytest.raises(SystemExit, match="was made otherwise"):
        tr.run_variant("cf2", str(tmp_path), "python", quick=False)


def test_bad_arguments_get_one_line(tmp_path, capsys):
    assert tr.main(["--out", str(tmp_path), "--variants", "nope"]) == 2
    assert capsys.readouterr().err.strip() == (
        f"error: --variants 'nope' is not a variant; allowed: {list(tr.VARIANTS)}"
    )
    assert tr.main(["--out", str(tmp_path), "--crazyflow-python", str(tmp_path / "none")]) == 2
    assert "is not a file" in capsys.readouterr().err
