"""Fault scenarios of issues 34 and 49, re-runnable: corrupt byte ranges of the newest
checkpoint and of a ``best/`` file, a second writer, a reader beside an unfinished save, and
with real ``python -m ttd3_jax.train`` processes (benchmarks/reliability_processes.py):
SIGKILL at chosen moments then ``--resume``, SIGINT / SIGTERM / SIGINT twice at chosen moments
then ``--resume OUT`` (each compared with an uninterrupted run), ``evaluate`` and ``export``
aimed at a stopped run's own files, a second trainer racing for a live run, and a full disk
(a small tmpfs; needs root, else skipped with a note).  Prints how each ended and exits 1
naming the cases that did not end as promised; docs/reliability.md holds measured outputs.

    python benchmarks/reliability.py            # 40 corruptions, 5 kill and 7 stop moments, 10 readers
    python benchmarks/reliability.py --quick    # 8 corruptions, 1 kill and 1 stop moment, 1 reader
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import tempfile
import time

import jax
import numpy as np
from reliability_processes import (  # beside this script
    full_disk,
    reference,
    sigint_then_resume,
    sigkill_then_resume,
)

from ttd3_jax.run import checkpoint as ckpt
from ttd3_jax.run import status


def state(seed: int) -> dict:
    rng = np.random.default_rng(seed)
    return {"buffer": rng.standard_normal((2048, 64)).astype(np.float32), "step": np.array([seed], np.int32),
            "actor": {"w": rng.standard_normal((64, 64)).astype(np.float32)}}  # fmt: skip


def flip(path: str, start: int, n: int, rng: np.random.Generator) -> None:
    """Change every byte of ``path[start : start + n]`` (XOR with random non-zero bytes)."""
    with open(path, "r+b") as fh:
        fh.seek(start)
        old = np.frombuffer(fh.read(n), np.uint8)
        fh.seek(start)
        fh.write((old ^ rng.integers(1, 256, old.size, dtype=np.uint8)).tobytes())


def corrupt_newest(trials: int, rng: np.random.Generator) -> dict:
    """A random range of a random file of checkpoint 2 (of 1 and 2) changed: does the
    restore fall back to 1, or load 2's true contents (damage unreported), or wrong contents?"""
    out = {"fell back": 0, "loaded intact": 0, "loaded WRONG contents": 0}
    for i in range(trials):
        with tempfile.TemporaryDirectory() as run_dir:
            m = ckpt.manager(run_dir)
            ckpt.save(m, 1, state(1))
            ckpt.save(m, 2, state(2))
            m.close()
            root = os.path.join(run_dir, "checkpoints", "2")
            files = sorted(os.path.join(d, f) for d, _, fs in os.walk(root) for f in fs)
            path = files[rng.integers(len(files))]
            size = os.path.getsize(path)
            start = int(rng.integers(max(size, 1)))
            n = int(min(rng.choice([1, 64, 4096]), max(size - start, 1)))
            flip(path, start, n, rng)
            epoch, got, _ = ckpt.restore_newest(run_dir, state(0))
            pairs = zip(jax.tree.leaves(got), jax.tree.leaves(state(2)), strict=True)
            same = all(np.array_equal(np.asarray(a), b) for a, b in pairs)
            key = "fell back" if epoch == 1 else "loaded intact" if same else "loaded WRONG contents"
            out[key] += 1
            print(f"  {i:>3} {os.path.relpath(path, root):<40} {n:>5} B at {start:>8}: {key}")
    return out


def corrupt_best(trials: int, rng: np.random.Generator) -> dict:
    out = {"detected": 0, "loaded intact": 0, "loaded WRONG contents": 0}
    policy = {"actor": {"w": np.arange(4096, dtype=np.float32)}, "obs_stats": None}
    with tempfile.TemporaryDirectory() as run_dir:
        for _ in range(trials):
            ckpt.save_policy(run_dir, 0, 1, 1.0, policy)
            path = os.path.join(run_dir, "best", "seed0.msgpack")
            data = bytearray(open(path, "rb").read())
            start = int(rng.integers(len(data) - 64))
            data[start : start + 64] = rng.bytes(64)
            open(path, "wb").write(bytes(data))
            try:
                got = ckpt.load_policy(run_dir, 0, policy)
                ok = np.array_equal(got["actor"]["w"], policy["actor"]["w"])
                out["loaded intact" if ok else "loaded WRONG contents"] += 1
            except ValueError:
                out["detected"] += 1
    return out


def two_writers_and_a_reader() -> dict:
    with tempfile.TemporaryDirectory() as run_dir:
        status.acquire(run_dir)
        try:
            status.acquire(run_dir)
            second = "ran beside the first"
        except status.RunLocked:
            second = "refused"
        status.release(run_dir)
        m = ckpt.manager(run_dir)
        ckpt.save(m, 1, state(1))
        m.close()
        tmp = os.path.join(run_dir, "checkpoints", "2.orbax-checkpoint-tmp-99")
        os.makedirs(tmp)
        ckpt.restore_newest(run_dir, state(0))
        return {
            "second writer": second,
            "trainer's unfinished save after a read": os.path.isdir(tmp) and "kept",
        }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--full-disk", type=int, default=0, metavar="N", help="only the full disk, N times")
    args = ap.parse_args()
    logging.getLogger("absl").setLevel(logging.ERROR)  # orbax's notes on read-only managers
    if args.full_disk:
        with tempfile.TemporaryDirectory() as tmp:
            for i in range(args.full_disk):
                print(full_disk(os.path.join(tmp, str(i)), os.path.join(tmp, "xla")), flush=True)
        return
    n, rng = (8 if args.quick else 40), np.random.default_rng(args.seed)
    failed = []

    def show(label: str, ok: bool, text) -> None:
        print(f"{label}: {text}", flush=True)
        if not ok:
            failed.append(label)

    print(f"corrupting checkpoint 2 of 2 ({n} trials):")
    newest = corrupt_newest(n, rng)
    show("newest checkpoint", newest["loaded WRONG contents"] == 0, newest)
    best = corrupt_best(n, rng)
    show("best/ file (64 random bytes)", best["loaded WRONG contents"] == 0, best)
    writers = two_writers_and_a_reader()
    show("writers", writers == {"second writer": "refused", "trainer's unfinished save after a read": "kept"},
         writers)  # fmt: skip
    t = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        cache = os.path.join(tmp, "xla")  # the runs share their compiled programs
        want, race = reference(tmp, cache)
        for name, outcome in sigkill_then_resume(tmp, cache, args.quick, want).items():
            show(f"SIGKILL {name}", "identical" in outcome, outcome)
        for label, (ok, outcome) in sigint_then_resume(tmp, cache, args.quick, want).items():
            show(label, ok, outcome)
        show("second trainer", race.startswith("exit 2: ") and "one writer per run" in race, race)
        if not args.quick:
            disk = full_disk(tmp, cache)["full disk"]
            show("full disk", disk.startswith("skipped") or (disk.startswith("exit 1;") and
                 "Traceback lines: 0;" in disk and disk.endswith("--resume exit 0")), disk)  # fmt: skip
    print(f"(train processes: {time.perf_counter() - t:.0f} s)")
    print(f"NOT as promised: {failed}" if failed else "every case ended as promised")
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
