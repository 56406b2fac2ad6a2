"""A run spec that trains in seconds, shared by the tests (not a test module)."""

from __future__ import annotations

from ttd3_jax.run import spec as sp


def tiny(**changes) -> sp.RunSpec:
    """``fast_dpg`` at a few seconds of training: 16 envs, 2 epochs of 16 vector steps, 32-32
    networks; ``changes`` are RunSpec or TrainConfig fields (:func:`ttd3_jax.run.spec.replace`).
    Without a model horizon, an epoch stays 16 vector steps whatever ``epochs`` is, so the
    tests' runs share one compiled epoch (through the suite's compilation cache)."""
    epochs = changes.get("epochs", 2)
    steps = 16 * max(epochs, 1) if isinstance(epochs, int) and not changes.get("model_horizon") else 32
    base = dict(num_envs=16, total_transitions=16 * (8 + steps), warmup_transitions=16 * 8,
                buffer_size=16 * 64, batch_size=64, updates_per_step=2, epochs=epochs,
                hidden=(32, 32))  # fmt: skip
    return sp.preset("fast_dpg", **{**base, **changes})


# the same run on the command line, with a 2-step model-based actor (the CLI's default preset)
TINY_CLI = [
    "--num-envs", "16", "--total-transitions", "1024", "--warmup-transitions", "128", "--buffer-size", "1024",
    "--batch-size", "64", "--updates-per-step", "2", "--epochs", "4", "--hidden", "32", "32",
    "--model-horizon", "2",
]  # fmt: skip
