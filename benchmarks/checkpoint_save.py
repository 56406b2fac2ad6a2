"""How long an epoch waits for its checkpoint: a synchronous save (written before the call
returns) against the trainer's background save (``ttd3_jax.run.checkpoint.save(..., wait=False)``
on an asynchronous manager: the state is copied to host memory, then written while the next
epoch trains).  The state is the ``fast`` preset's whole train state with 2 critic updates per
rollout (as ``robust`` and ``cf2`` train: their replay buffer of 450k transitions is most of
it; ``fast`` itself keeps no buffer), saved alternately both ways into a temporary directory.

    python benchmarks/checkpoint_save.py            # 7 saves each way
    python benchmarks/checkpoint_save.py --quick    # CI smoke run: 2 each

Prints the median seconds the caller is blocked per save and their ratio, and appends a
record to ``benchmarks/results/checkpoint_save.jsonl``.  The background write still costs
CPU time; it overlaps with training instead of adding to it.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time

import jax

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _peers  # noqa: E402

from ttd3_jax.run import checkpoint as ckpt  # noqa: E402
from ttd3_jax.run import spec as sp  # noqa: E402
from ttd3_jax.run.sharding import runner_fns  # noqa: E402
from ttd3_jax.td3.trainer import seed_keys  # noqa: E402


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--saves", type=int, default=7, help="saves each way (default 7)")
    ap.add_argument("--quick", action="store_true", help="CI smoke run: 2 saves each way")
    ap.add_argument("--out", default="benchmarks/results/checkpoint_save.jsonl")
    args = ap.parse_args(argv)
    n = 2 if args.quick else args.saves
    if n < 1:
        ap.error(f"--saves must be >= 1, got {n}")
    s = sp.preset("fast", updates_per_step=2)  # with critics, as robust and cf2: the buffer is most of it
    keys = seed_keys(s.seed, s.num_seeds)
    init_fn = runner_fns(sp.trainer_for(s), keys, s.hp)[0]
    ts = jax.block_until_ready(init_fn(keys, s.hp))
    mbytes = sum(x.nbytes for x in jax.tree.leaves(ts)) / 1e6
    blocked = {"sync": [], "background": []}
    written = []  # background: seconds from the call until the checkpoint is on disk
    with tempfile.TemporaryDirectory() as tmp:
        sync = ckpt.manager(os.path.join(tmp, "sync"))
        bg = ckpt.manager(os.path.join(tmp, "bg"), asynchronous=True)
        for i in range(n):  # alternate, so both see the same machine load
            t = time.perf_counter()
            ckpt.save(sync, i, ts)
            blocked["sync"].append(time.perf_counter() - t)
            t = time.perf_counter()
            ckpt.save(bg, i, ts, wait=False)
            blocked["background"].append(time.perf_counter() - t)
            ckpt.finish(bg)
            written.append(time.perf_counter() - t)
    med = {k: statistics.median(v) for k, v in blocked.items()}
    record = _peers.machine_record(argv)
    record.update(state_mb=mbytes, saves=n,
                  quick=args.quick, blocked_s=blocked, background_written_s=written)  # fmt: skip
    print(f"fast train state: {mbytes:.1f} MB; {n} saves each way, alternating ({record['cpu']}, "
          f"{record['cpus']} cpus)")  # fmt: skip
    print(f"blocked per save, median: synchronous {med['sync']:.3f} s, background {med['background']:.3f} s "
          f"(ratio {med['sync'] / med['background']:.1f}x); the background write took "
          f"{statistics.median(written):.3f} s to reach the disk")  # fmt: skip
    _peers.append_record(args.out, record)
    return record


if __name__ == "__main__":
    main()
