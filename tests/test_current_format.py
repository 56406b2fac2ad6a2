"""experiments/current_format.py: a config.json written by the long runs' pinned commit
(format 14) or by format 15 becomes the current format's file, and only a format change is
rewritten."""

from __future__ import annotations

import copy
import glob
import json
import os

import pytest
from experiment_scripts import experiment

from ttd3_jax.run import spec as sp

HERE = os.path.dirname(os.path.abspath(__file__))


@pytest.fixture(scope="module")
def current() -> dict:
    path = sorted(
        glob.glob(os.path.join(HERE, "..", "results", "mujoco", "runs", "ant-ttd3", "*", "config.json"))
    )[0]
    with open(path) as fh:
        return json.load(fh)


def test_formats_14_and_15_become_the_current_file(current):
    cf = experiment("current_format")
    assert current["format"] == sp.CONFIG_FORMAT
    f14 = copy.deepcopy(current)
    f14["format"] = 14
    del f14["train"]["selection"]
    assert cf.rewrite(f14) == current
    f15 = copy.deepcopy(current)  # the side branch's format 15: disturbance_tau, off
    f15["format"] = 15
    f15["task"]["observation"]["disturbance_tau"] = 0.0
    assert cf.rewrite(f15) == current
    assert cf.rewrite(current) == current


def test_anything_but_a_format_change_is_refused(current):
    cf = experiment("current_format")
    on = copy.deepcopy(current)
    on["format"] = 15
    on["task"]["observation"]["disturbance_tau"] = 0.5
    with pytest.raises(ValueError, match="disturbance_tau is set"):
        cf.rewrite(on)
    old = dict(current, format=13)
    with pytest.raises(ValueError, match="config format 13"):
        cf.rewrite(old)
    bad = copy.deepcopy(current)
    bad["format"] = 14
    bad["train"]["no_such_field"] = 1
    with pytest.raises(ValueError):
        cf.rewrite(bad)
