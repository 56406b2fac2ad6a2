"""Stored traced programs (:class:`ttd3_jax.run.cache.StoredProgram`): a warm launch loads the
program instead of tracing it, and runs the same bits as plain ``jit``."""

from __future__ import annotations

import dataclasses
import hashlib
import os
import pickle

import jax
import numpy as np
import pytest
from tiny import tiny

from ttd3_jax.run import loop
from ttd3_jax.run import spec as sp
from ttd3_jax.run.cache import StoredProgram, program_store
from ttd3_jax.run.sharding import runner_fns
from ttd3_jax.td3.trainer import seed_keys


def digest(tree) -> str:
    h = hashlib.sha256()
    for x in jax.tree.leaves(tree):
        h.update(np.asarray(jax.random.key_data(x) if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)
                            else x).tobytes())  # fmt: skip
    return h.hexdigest()


class Counting:
    """``fn`` that counts how often it is traced (called with tracers)."""

    def __init__(self, fn):
        self.fn, self.calls = fn, 0

    def __call__(self, *args):
        self.calls += 1
        return self.fn(*args)


def programs(spec: sp.RunSpec, directory: str):
    keys = seed_keys(spec.seed, spec.num_seeds)
    init_fn, epoch_fn, eval_fn, _ = runner_fns(sp.trainer_for(spec), keys, spec.hp)
    wrapped = [Counting(f) for f in (init_fn, epoch_fn, eval_fn)]
    names, donate = ("init", "epoch", "eval"), ((), (0,), ())
    stored = [StoredProgram(f, n, repr(spec), directory, donate_argnums=d)
              for f, n, d in zip(wrapped, names, donate, strict=True)]  # fmt: skip
    return keys, (init_fn, epoch_fn, eval_fn), stored, wrapped


def train_one_epoch(keys, hp, init_fn, epoch_fn, eval_fn, lower):
    """init, one epoch and an evaluation; ``lower`` compiles each function for its arguments."""
    ts = lower(init_fn, keys, hp)(keys, hp)
    first = digest(ts)
    ev_c = lower(eval_fn, jax.eval_shape(lambda t: t, ts))
    ts, m = lower(epoch_fn, ts, hp)(ts, hp)  # donates the state
    return first, digest((ts, m)), digest(ev_c(ts))


@pytest.mark.slow  # .ci/run runs it (-m slow)
def test_a_stored_program_runs_the_bits_of_jit_and_a_warm_load_does_not_trace(tmp_path):
    spec = tiny(model_horizon=2)
    keys, plain, _, _ = programs(spec, str(tmp_path))
    want = train_one_epoch(keys, spec.hp, *plain, lambda f, *a: f.lower(*a).compile())
    for launch in ("cold", "warm"):  # a fresh StoredProgram, as a new process makes
        keys, _, stored, counted = programs(spec, str(tmp_path))
        got = train_one_epoch(keys, spec.hp, *stored, lambda f, *a: f.lower(*a).compile())
        assert got == want, launch
        assert [c.calls for c in counted] == ([1, 1, 1] if launch == "cold" else [0, 0, 0]), launch
    assert sorted(f.split("-")[0] for f in os.listdir(tmp_path)) == ["epoch", "eval", "init"]
    # the outputs' shapes without tracing (the runner's resume asks for the state's)
    init_s = stored[0]
    assert jax.tree.structure(init_s.eval_shape(keys, spec.hp)) == jax.tree.structure(
        jax.eval_shape(plain[0], keys, spec.hp)
    )
    assert counted[0].calls == 0


def test_another_context_or_argument_shape_is_another_program(tmp_path):
    spec = tiny(model_horizon=2)
    keys, _, (init_s, _, _), _ = programs(spec, str(tmp_path))
    other = StoredProgram(init_s.fn, "init", repr(dataclasses.replace(spec, num_seeds=2)), str(tmp_path))
    assert other.path((keys, spec.hp)) != init_s.path((keys, spec.hp))
    two = seed_keys(0, 2)
    assert init_s.path((two, spec.hp)) != init_s.path((keys, spec.hp))
    assert init_s.path((keys, spec.hp)) == programs(spec, str(tmp_path))[2][0].path((keys, spec.hp))


def _corrupt(path: str, how: str) -> None:
    with open(path, "rb") as fh:
        data = bytearray(fh.read())
    if how == "torn":
        data = data[: len(data) // 2]
    elif how == "flipped":  # one byte of the program, past the header
        data[-100] ^= 0xFF
    elif how == "foreign":  # what format 1 wrote: a pickle
        data = bytearray(pickle.dumps({"exported": b"", "out_tree": None}))
    with open(path, "wb") as fh:
        fh.write(bytes(data))


@pytest.mark.parametrize("how", ["torn", "flipped", "foreign"])
def test_a_stored_file_that_does_not_load_is_traced_again(tmp_path, how):
    spec = tiny(model_horizon=2)
    keys, (init_fn, _, _), (init_s, _, _), counted = programs(spec, str(tmp_path))
    want = digest(init_fn(keys, spec.hp))
    init_s.lower(keys, spec.hp)  # traced and stored
    path = init_s.path((keys, spec.hp))
    size = os.path.getsize(path)
    _corrupt(path, how)
    keys, _, (init_s, _, _), counted = programs(spec, str(tmp_path))  # a new launch
    with pytest.warns(UserWarning, match="does not load.*tracing it again"):
        got = init_s.lower(keys, spec.hp).compile()(keys, spec.hp)
    assert digest(got) == want and counted[0].calls == 1
    assert os.path.getsize(path) == size  # replaced by the traced program


def test_a_program_with_a_host_callback_runs_as_plain_jit(tmp_path, capfd, shown_messages):
    """``jax.debug.print`` in a stored function: not stored, a one-line note, and it runs."""

    def noisy(x):
        jax.debug.print("sum {s}", s=x.sum())
        return {"y": x * 2}

    fn = Counting(noisy)
    stored = StoredProgram(fn, "noisy", "ctx", str(tmp_path), donate_argnums=(0,))
    x = jax.numpy.arange(3.0)
    out = stored.lower(x).compile()(x)
    jax.effects_barrier()
    err = capfd.readouterr()
    assert "sum 3.0" in err.out and err.err.count("note: the noisy program cannot be stored") == 1
    assert np.array_equal(out["y"], [0.0, 2.0, 4.0])
    assert jax.tree.structure(stored.eval_shape(jax.numpy.arange(3.0))) == jax.tree.structure(out)
    assert os.listdir(tmp_path) == []


def _track_csv(path, amplitude: float) -> None:
    t = np.arange(0, 3.01, 0.05)
    rows = [f"{a:.2f},{amplitude * np.sin(a):.4f},{amplitude * np.cos(a) - amplitude:.4f},{0.1 * a:.4f}"
            for a in t]  # fmt: skip
    with open(path, "w") as fh:
        fh.write("t,x,y,z\n" + "\n".join(rows) + "\n")


@pytest.mark.slow  # .ci/run runs it (-m slow)
def test_a_training_csv_edited_in_place_is_traced_again_and_trains_on_its_new_contents(tmp_path, monkeypatch):
    """The issue's sequence: a run on a training-track CSV, the CSV edited in place (same
    length), the same run again: it traces again and equals plain jit on the new track."""
    monkeypatch.setattr(loop, "program_store", lambda: str(tmp_path / "store"))
    csv = tmp_path / "track.csv"
    _track_csv(csv, 1.0)
    spec = tiny()
    spec = dataclasses.replace(spec, task=spec.task.replace(train_tracks=(str(csv),),
                                                              train_tracks_weight=1.0))  # fmt: skip
    compile_ = lambda f, *x: f.lower(*x).compile()  # noqa: E731

    def launch(stored: bool):
        keys = seed_keys(spec.seed, spec.num_seeds)
        raw = runner_fns(sp.trainer_for(spec), keys, spec.hp)
        counted = tuple(Counting(f) for f in raw[:3]) + raw[3:]
        fns = loop._stored(spec, counted) if stored else raw
        return train_one_epoch(keys, spec.hp, *fns[:3], compile_), [c.calls for c in counted[:3]]

    first, calls = launch(stored=True)
    assert calls == [1, 1, 1]
    size = os.path.getsize(csv)
    _track_csv(csv, 2.0)  # edited in place, the same length
    assert os.path.getsize(csv) == size
    got, calls = launch(stored=True)
    assert calls == [1, 1, 1]  # traced again
    want, _ = launch(stored=False)
    assert got == want and got != first


def test_no_store_under_key_reuse_checks_or_without_the_compilation_cache():
    assert program_store() == os.path.join(jax.config.jax_compilation_cache_dir, "traced")
    with jax.debug_key_reuse(True):
        assert program_store() is None
    jax.config.update("jax_enable_compilation_cache", False)
    try:
        assert program_store() is None
    finally:
        jax.config.update("jax_enable_compilation_cache", True)


@pytest.mark.slow  # .ci/run runs it (-m slow)
def test_the_runner_loads_one_seeds_programs_for_another_seed_and_learning_rate(tmp_path, monkeypatch):
    """The runner's key leaves out the seed and the hyperparameter values (traced
    arguments): seed 1 with another learning rate loads seed 0's programs and runs what
    plain jit runs for it."""
    monkeypatch.setattr(loop, "program_store", lambda: str(tmp_path))
    a = tiny(model_horizon=2)
    b = dataclasses.replace(a, seed=1, hp=dataclasses.replace(a.hp, lr_actor=3e-3, sigma=0.2))
    compile_ = lambda f, *x: f.lower(*x).compile()  # noqa: E731

    def fns(spec):
        keys = seed_keys(spec.seed, spec.num_seeds)
        return keys, runner_fns(sp.trainer_for(spec), keys, spec.hp)

    keys, plain = fns(b)
    want = train_one_epoch(keys, b.hp, *plain[:3], compile_)
    keys_a, stored_a = fns(a)
    train_one_epoch(keys_a, a.hp, *loop._stored(a, stored_a)[:3], compile_)  # cold: traced, stored
    keys, raw = fns(b)
    counted = tuple(Counting(f) for f in raw[:3]) + raw[3:]
    stored_b = loop._stored(b, counted)
    assert all(isinstance(f, StoredProgram) for f in stored_b[:3])
    assert train_one_epoch(keys, b.hp, *stored_b[:3], compile_) == want
    assert [c.calls for c in counted[:3]] == [0, 0, 0]
