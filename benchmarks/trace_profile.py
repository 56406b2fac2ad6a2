"""Where the trace of the ``fast`` preset's epoch program goes (issue 51): ``cProfile`` of
``jax.jit(trainer.epoch).lower(...)`` on the train state's shapes, printing the whole
lowering's seconds and the cumulative seconds of the package's functions on its path (the
rest is jax: differentiating the rollout's scan, partial evaluation, transposition and the
lowering to StableHLO).  A profile slows what it measures; compare the shares, not the
seconds, with ``time_to_tracker.py``'s trace rows.

    python benchmarks/trace_profile.py            # the epoch program
    python benchmarks/trace_profile.py --program eval
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import time

import jax

from ttd3_jax.run import spec as sp
from ttd3_jax.td3.trainer import seed_keys


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--program", choices=("epoch", "eval"), default="epoch")
    ap.add_argument("--top", type=int, default=12, help="package functions to list")
    args = ap.parse_args(argv)
    spec = sp.preset("fast")
    trainer = sp.trainer_for(spec)
    state = jax.eval_shape(trainer.init, seed_keys(0, 1)[0], spec.hp)
    lower = {
        "epoch": lambda: jax.jit(trainer.epoch).lower(state, spec.hp),
        "eval": lambda: jax.jit(trainer.evaluate).lower(state),
    }[args.program]
    prof = cProfile.Profile()
    t = time.perf_counter()
    prof.enable()
    lower()
    prof.disable()
    total = time.perf_counter() - t
    stats = pstats.Stats(prof).stats  # {(file, line, name): (calls, prim calls, tottime, cumtime, callers)}
    ours = sorted(
        ((v[3], f"{k[0].split('ttd3_jax/')[-1]}:{k[2]}") for k, v in stats.items() if "/ttd3_jax/" in k[0]),
        reverse=True,
    )
    print(f"{args.program} program of the fast preset: lowering {total:.2f} s under cProfile")
    print(f"{'cumulative s':>12} {'share':>6}  package function")
    for cum, name in ours[: args.top]:
        print(f"{cum:12.2f} {cum / total:6.0%}  {name}")


if __name__ == "__main__":
    main()
