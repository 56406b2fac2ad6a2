"""Where the per-env constants of ``ttd3_jax.run.memory`` come from: XLA:CPU's
``memory_analysis()`` of the compiled init, epoch and evaluation programs of the ``fast`` and
``fast_dpg`` presets at a few sizes, beside the estimate ``memory.needs`` makes for them.

    python benchmarks/memory_calibration.py

The epoch's temporaries grow with envs x rollout steps for ``fast`` (about 3.7 KB per env
and rollout step on jax 0.10.2: ``memory.ROLLOUT_STEP_BYTES``) and the init program's with
the envs (about 12 KB per env: ``memory.ENV_STEP_BYTES``); compare the rows to check them.
"""

from __future__ import annotations

import jax

from ttd3_jax.run import memory
from ttd3_jax.run import spec as sp
from ttd3_jax.td3.trainer import seed_keys

MIB = 2**20
BASE = dict(total_transitions=20_000_000, buffer_size=10_000, warmup_transitions=10_000, epochs=100)


def analyse(preset: str, **changes) -> None:
    s = sp.preset(preset, **BASE, **changes)
    t = sp.trainer_for(s)
    keys = seed_keys(0, s.num_seeds)
    init = jax.jit(jax.vmap(t.init, in_axes=(0, None)))
    ts = jax.eval_shape(init, keys, s.hp)
    programs = {
        "init": init.lower(keys, s.hp),
        "epoch": jax.jit(jax.vmap(t.epoch, in_axes=(0, None))).lower(ts, s.hp),
        "eval": jax.jit(jax.vmap(t.evaluate)).lower(ts),
    }
    temp = {k: p.compile().memory_analysis().temp_size_in_bytes / MIB for k, p in programs.items()}
    rows = getattr(t.env.env, "num_segments", None)
    est = {n.what: n.bytes / MIB for n in memory.needs(s, t.env.obs_size, t.env.action_size, rows)}
    size = f"{s.num_seeds} seed(s) x {s.train.num_envs} envs, horizon {s.train.model_horizon}"
    print(f"{preset:9s} {size:32s} temp MiB: " + ", ".join(f"{k} {v:.1f}" for k, v in temp.items()))
    print(f"{'':9s} {'':32s} estimate MiB: " + ", ".join(f"{k} {v:.1f}" for k, v in est.items()))


if __name__ == "__main__":
    print(f"jax {jax.__version__}, {jax.devices()[0].device_kind}")
    analyse("fast")
    analyse("fast", num_envs=1024)
    analyse("fast", num_seeds=8)
    analyse("fast_dpg", num_envs=1024)
