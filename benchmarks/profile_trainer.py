"""Where a trainer epoch's time goes on CPU: per-kernel times of one compiled epoch.

Runs one case of ``trainer_throughput.py`` (default ``paper``: the paper preset, 3 seeds
vmapped) under ``jax.profiler`` with XLA:CPU's per-kernel trace events switched on, and
prints each kernel's time per gradient update (all seeds together), largest first, with
how often it ran per update and the notable opcodes inside (as ``profile_env.py`` does).
The profiler adds about 2 µs per kernel, so read the ranking and the shares, not the sum.

    python benchmarks/profile_trainer.py                 # the paper preset's epoch
    python benchmarks/profile_trainer.py --case net256 --top 30
    python benchmarks/profile_trainer.py --quick         # smoke run (CI)
"""

from __future__ import annotations

import os

# must be set before jax is imported: XLA:CPU then emits one trace event per kernel
os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_enable_xprof_traceme=true").strip()

import argparse  # noqa: E402
import collections  # noqa: E402
import glob  # noqa: E402
import gzip  # noqa: E402
import json  # noqa: E402
import re  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402

import jax  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import trainer_throughput as tt  # noqa: E402
from profile_env import kernel_contents  # noqa: E402

from ttd3_jax.run import spec as sp  # noqa: E402
from ttd3_jax.td3.trainer import seed_keys  # noqa: E402


def compiled_epoch(case: str, quick: bool):
    s, vmapped = tt.cases(quick)[case]
    t = sp.trainer_for(s)
    keys = seed_keys(s.seed, s.num_seeds)
    if vmapped:
        ts = jax.jit(jax.vmap(t.init, in_axes=(0, None)))(keys, s.hp)
        epoch = jax.vmap(t.epoch, in_axes=(0, None))
    else:
        ts, epoch = jax.jit(t.init)(keys[0], s.hp), t.epoch
    return s, jax.jit(epoch).lower(ts, s.hp).compile(), ts


def matmul_kernels(hlo: str) -> set[str]:
    """Kernels that multiply matrices: ``dot`` instructions and fusions (YNNPACK's among
    them) whose computation holds one."""
    bodies = dict(re.findall(r"\n(%[\w.\-]+) [^\n]*\{\n(.*?)\n\}", hlo, re.S))
    out = set(re.findall(r"\n\s*(?:ROOT )?%?([\w.\-]+) = \S+ dot\(", hlo))
    for name, comp in re.findall(r"(%[\w.\-]+) = [^\n]* fusion\([^\n]*calls=(%[\w.\-]+)", hlo):
        if " dot(" in bodies.get(comp, ""):
            out.add(name[1:])
    return out


def trace_events(compiled, *args) -> list[dict]:
    jax.block_until_ready(compiled(*args))
    with tempfile.TemporaryDirectory() as d:
        jax.profiler.start_trace(d, create_perfetto_trace=True)
        jax.block_until_ready(compiled(*args))
        jax.profiler.stop_trace()
        (path,) = glob.glob(os.path.join(d, "**", "perfetto_trace.json.gz"), recursive=True)
        events = json.load(gzip.open(path))
    return events["traceEvents"] if isinstance(events, dict) else events


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", default="paper")
    ap.add_argument("--top", type=int, default=25)
    ap.add_argument("--quick", action="store_true", help="tiny sizes, to keep the script alive in CI")
    ap.add_argument("--hlo", default=None, help="write the optimised HLO text here")
    args = ap.parse_args(argv)
    s, compiled, ts = compiled_epoch(args.case, args.quick)
    hlo = compiled.as_text()
    if args.hlo:
        open(args.hlo, "w").write(hlo)
    contents, mm = kernel_contents(hlo), matmul_kernels(hlo)
    ops = dict(re.findall(r"\n\s*(?:ROOT )?%?([\w.\-]+) = \S+ ([a-z\-]+)\(", hlo))
    total, count = collections.Counter(), collections.Counter()
    for e in trace_events(compiled, ts, s.hp):
        name = e.get("name", "")
        if e.get("ph") == "X" and "::" not in name and not name.startswith(("end:", "$")):
            total[name] += e["dur"]
            count[name] += 1
    n_upd = s.train.steps_per_epoch * s.train.updates_per_step
    wall = sum(total.values())
    print(f"case={args.case} seeds={s.num_seeds} updates/seed={n_upd} device={jax.devices()[0].platform}")
    print(f"{'kernel':<36} {'us/upd':>8} {'share':>6} {'runs/upd':>8}  op / contains")
    for name, us in total.most_common(args.top):
        what = ("matmul " if name in mm else "") + (contents.get(name) or ops.get(name, ""))
        print(f"{name[:36]:<36} {us / n_upd:>8.1f} {us / wall:>6.1%} {count[name] / n_upd:>8.2f}  {what}")
    leaf = {n: us for n, us in total.items() if not n.startswith(("while", "cond", "call"))}  # not loops
    mm_us = sum(us for n, us in leaf.items() if n in mm)
    print(f"matmuls: {mm_us / sum(leaf.values()):.1%} of the kernels' time (loops and branches left out)")
    print(f"{len(total)} kernels, {wall / n_upd:.0f} us per update in all (profiled)")


if __name__ == "__main__":
    main()
