"""How soon the ``fast`` preset beats the paper: a sweep of its actor learning rate and its
decay (``Hyper`` leaves: one compiled program, ``vmap``ped over seeds x learning rates x
decays), for each static variant of the env count, the rollout horizon, the warm-up and the
budget (a program each).

Every run evaluates after each epoch of ``--epoch-rollouts`` actor updates (one per rollout of
every env, so variants with other env counts compare at equal updates); the table gives,
per variant, learning rate and decay, the transitions (and epoch) after which all seeds beat the
paper's T-TD3 on both test tracks, each seed's first such epoch, and the last epoch's worst
seed against the paper and our NMPC (``ttd3_jax.control.paper``'s figures).

    python experiments/fast_sweep.py                       # the study in docs/performance.md
    python experiments/fast_sweep.py --variants preset e64_960k --lrs 1e-2 2e-2
    python experiments/fast_sweep.py --quick           # CI smoke run
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

from ttd3_jax.control.paper import PAPER_TTD3
from ttd3_jax.run import spec as sp
from ttd3_jax.td3.trainer import seed_keys

NMPC = {"spiral": 5.04, "los": 198.12}  # our NMPC on the test tracks (README; evaluate --controller nmpc)
PAPER = {"spiral": PAPER_TTD3["spiral_tracking_error"], "los": PAPER_TTD3["los_tracking_error"]}
# name: TrainConfig changes of the fast preset (16 envs, 480k transitions, a warm-up of 4 rollouts)
VARIANTS = {
    "preset": {},
    # c0d0d59's preset (with --lrs 2e-2): 64 envs, 960k transitions, the warm-up's 10k in 4 rollouts
    "e64_960k": {"num_envs": 64, "total_transitions": 960_000, "warmup_transitions": 10_000},
    "e32": {"num_envs": 32, "warmup_transitions": 6_400},
    "e8_240k": {"num_envs": 8, "total_transitions": 240_000, "warmup_transitions": 1_600},
    "320k": {"total_transitions": 320_000},
    "w0": {"warmup_transitions": 0},
    "h25": {"model_horizon": 25},  # 0.25 s rollouts: twice the updates per transition
    "h100": {"model_horizon": 100},  # 1 s rollouts
}


def sweep(variant: str, cells: list[tuple[float, float]], seeds: int, epoch_rollouts: int,
          total: int | None = None) -> dict:  # fmt: skip
    """Spiral-RT and LOS-RT after every epoch of ``epoch_rollouts`` actor updates (rollouts),
    (epochs, cells, seeds) each; a cell is a (learning rate, decay); ``total``: another budget
    than the variant's."""
    spec = sp.preset("fast", **{**VARIANTS[variant], **({"total_transitions": total} if total else {})})
    per_epoch = epoch_rollouts * spec.train.num_envs * spec.train.model_horizon
    spec = sp.replace(spec, epochs=max(1, spec.train.total_transitions // per_epoch))
    epochs = spec.train.epochs
    trainer = sp.trainer_for(spec)
    keys = jnp.tile(seed_keys(0, seeds), (len(cells), 1))  # (cells * seeds, 2): cell-major
    hp = jax.tree.map(lambda x: jnp.full((len(cells) * seeds,), x, jnp.float32), spec.hp)
    lrs, decays = (jnp.repeat(jnp.asarray(x, jnp.float32), seeds) for x in zip(*cells, strict=True))
    hp = hp.replace(lr_actor=lrs, lr_decay=decays)
    init = jax.jit(jax.vmap(trainer.init))
    epoch = jax.jit(jax.vmap(trainer.epoch), donate_argnums=0)
    evaluate = jax.jit(jax.vmap(trainer.evaluate))
    t = time.perf_counter()
    ts = init(keys, hp)
    out = {"spiral": [], "los": [], "transitions": []}
    for _ in range(epochs):
        ts, m = epoch(ts, hp)
        ev = jax.device_get(evaluate(ts))
        out["spiral"].append(np.asarray(ev["spiral_tracking_error"]).reshape(len(cells), seeds))
        out["los"].append(np.asarray(ev["los_tracking_error"]).reshape(len(cells), seeds))
        out["transitions"].append(int(np.asarray(ts.n_tr)[0]))
    out["wall_s"] = time.perf_counter() - t
    return {k: np.asarray(v) if k != "wall_s" else v for k, v in out.items()}


def first_beat(spiral: np.ndarray, los: np.ndarray) -> np.ndarray:
    """Per seed, the first epoch index (0-based) beating the paper on both tracks, or -1."""
    beat = (spiral <= PAPER["spiral"]) & (los <= PAPER["los"])  # (epochs, seeds)
    return np.where(beat.any(axis=0), beat.argmax(axis=0), -1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--lrs", nargs="+", type=float, default=[5e-3, 1e-2, 2e-2])
    ap.add_argument("--decays", nargs="+", type=float, default=[1.0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--epoch-rollouts", type=int, default=20, help="evaluate every this many actor updates")
    ap.add_argument("--out", default="benchmarks/results/fast_sweep.jsonl")
    ap.add_argument("--quick", action="store_true", help="one cell, one seed, 16k transitions (CI)")
    a = ap.parse_args()
    if a.quick:
        a.variants, a.lrs, a.decays, a.seeds, a.out = ["preset"], [1e-2], [1.0], 1, ""
        a.epoch_rollouts = 10
    cells = [(lr, d) for lr in a.lrs for d in a.decays]
    print(f"{'variant':>10} {'lr':>7} {'decay':>5} {'all beat at':>12} {'per seed (epoch)':>18} "
          f"{'last: worst Spiral':>19} {'worst LOS':>10} {'< NMPC':>7}")  # fmt: skip
    for v in a.variants:
        r = sweep(v, cells, a.seeds, a.epoch_rollouts, total=16_000 if a.quick else None)
        for i, (lr, decay) in enumerate(cells):
            sp_, los = r["spiral"][:, i], r["los"][:, i]
            first = first_beat(sp_, los)
            all_at = "never" if (first < 0).any() else f"{r['transitions'][first.max()]:,}"
            ws, wl = float(np.nanmax(sp_[-1])), float(np.nanmax(los[-1]))
            below = ws < NMPC["spiral"] and wl < NMPC["los"]
            seeds_s = " ".join(str(f + 1) if f >= 0 else "-" for f in first)
            row = f"{v:>10} {lr:7.0e} {decay:5.2f} {all_at:>12} {seeds_s:>18} {ws:19.2f} {wl:10.2f}"
            print(f"{row} {str(below):>7}", flush=True)
            rec = dict(time=time.strftime("%Y-%m-%d %H:%M"), variant=v, lr_actor=lr, lr_decay=decay,
                       seeds=a.seeds, epoch_rollouts=a.epoch_rollouts,
                       transitions=r["transitions"].tolist(), spiral=sp_.tolist(), los=los.tolist(),
                       wall_s=r["wall_s"])  # fmt: skip
            if a.out:
                with open(a.out, "a") as fh:
                    fh.write(json.dumps(rec) + "\n")


if __name__ == "__main__":
    main()
