"""Compile time of the ``fast`` preset's three programs (init, epoch, eval) under XLA:CPU
flags, side by side in one run, with what each flag does to the run time.

Each case is a fresh process with no compilation cache: it builds the trainer, traces
(lowers) and compiles the programs one after the other (``threads``: traces them one after
the other, then compiles the three in threads at once), then times the warm-up and two
epochs and evaluates the policy, so a flag that compiles faster but runs slower, or changes
what is learned, shows.  Cases run interleaved, ``--repeats`` rounds; the table gives the
median per case and its ratio to ``xla_defaults`` (XLA's own flags; ``ttd3_jax``: the flags
:mod:`ttd3_jax.compile_flags` sets).

    python benchmarks/compile_time.py                     # all cases, 2 rounds
    python benchmarks/compile_time.py --cases xla_defaults ttd3_jax --repeats 3
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

FUSION_ON, FUSION_OFF = "--xla_cpu_use_fusion_emitters=true", "--xla_cpu_use_fusion_emitters=false"
OPT3, OPT1 = "--xla_backend_optimization_level=3", "--xla_backend_optimization_level=1"  # 3: XLA's default
CASES = {  # name: (XLA_FLAGS, compile the three programs in threads at once)
    "xla_defaults": (f"{FUSION_ON} {OPT3}", False),  # (naming a flag keeps ttd3_jax.compile_flags off it)
    "xla_defaults_threads": (f"{FUSION_ON} {OPT3}", True),
    "no_fusion_emitters": (f"{FUSION_OFF} {OPT3}", False),
    "opt_level_1": (f"{FUSION_ON} {OPT1}", False),
    "opt_level_0": (f"{FUSION_ON} --xla_backend_optimization_level=0", False),
    "fast_compile_preset": (f"{FUSION_ON} {OPT3} --xla_cpu_opt_preset=CPU_OPT_PRESET_FAST_COMPILE", False),
    "ttd3_jax": ("", False),  # the flags ttd3_jax.compile_flags sets: fusion emitters off, level 1
    "ttd3_jax_threads": ("", True),
}
STAGES = ("init_lower", "init_compile", "epoch_lower", "epoch_compile", "eval_lower", "eval_compile",
          "compile_sum", "warmup_run", "epoch_run", "spiral", "los")  # fmt: skip

CHILD = r"""
import json, sys, threading, time
t0 = time.perf_counter()
import jax
jax.config.update("jax_enable_compilation_cache", False)
from ttd3_jax.run import spec as sp
from ttd3_jax.run.sharding import runner_fns
from ttd3_jax.td3.trainer import seed_keys

threads = sys.argv[1] == "1"
spec = sp.preset("fast", epochs=10)
trainer = sp.trainer_for(spec)
keys, hp = seed_keys(0, 1), spec.hp
init_fn, epoch_fn, eval_fn, _ = runner_fns(trainer, keys, hp)
out = {}

def build(name, fn, args):
    t = time.perf_counter()
    low = fn.lower(*args)
    t1 = time.perf_counter()
    exe = low.compile()
    out[name + "_lower"], out[name + "_compile"] = t1 - t, time.perf_counter() - t1
    return exe

ts_shape = jax.eval_shape(init_fn, keys, hp)
if threads:  # lower the three one after the other (tracing holds the GIL), compile them at once
    lowered = {}
    for name, fn, args in (("init", init_fn, (keys, hp)), ("epoch", epoch_fn, (ts_shape, hp)),
                           ("eval", eval_fn, (ts_shape,))):
        t = time.perf_counter()
        lowered[name] = fn.lower(*args)
        out[name + "_lower"] = time.perf_counter() - t
    exes = {}

    def comp(name):
        t = time.perf_counter()
        exes[name] = lowered[name].compile()
        out[name + "_compile"] = time.perf_counter() - t

    t = time.perf_counter()
    ths = [threading.Thread(target=comp, args=(n,)) for n in lowered]
    for th in ths:
        th.start()
    for th in ths:
        th.join()
    out["parallel_wall"] = time.perf_counter() - t
    init_c, epoch_c, eval_c = exes["init"], exes["epoch"], exes["eval"]
else:
    init_c = build("init", init_fn, (keys, hp))
    epoch_c = build("epoch", epoch_fn, (ts_shape, hp))
    eval_c = build("eval", eval_fn, (ts_shape,))
t = time.perf_counter()
ts = jax.block_until_ready(init_c(keys, hp))
out["warmup_run"] = time.perf_counter() - t
t = time.perf_counter()
for _ in range(2):
    ts, m = epoch_c(ts, hp)
jax.block_until_ready(m)
out["epoch_run"] = (time.perf_counter() - t) / 2
ev = jax.device_get(eval_c(ts))
out["spiral"], out["los"] = float(ev["spiral_tracking_error"][0]), float(ev["los_tracking_error"][0])
print("RESULT " + json.dumps(out))
"""


def run_case(flags: str, threads: bool) -> dict:
    env = dict(os.environ)
    env["XLA_FLAGS"] = " ".join(f for f in (env.get("XLA_FLAGS", ""), flags) if f)
    p = subprocess.run([sys.executable, "-c", CHILD, "1" if threads else "0"], env=env, capture_output=True,
                       text=True)  # fmt: skip
    line = [x for x in p.stdout.splitlines() if x.startswith("RESULT ")]
    if p.returncode or not line:
        raise SystemExit(f"case with XLA_FLAGS={flags!r} failed:\n{p.stderr[-2000:]}")
    r = json.loads(line[0][len("RESULT ") :])
    r["compile_sum"] = sum(r[k] for k in ("init_lower", "init_compile", "epoch_lower", "epoch_compile",
                                           "eval_lower", "eval_compile"))  # fmt: skip
    if "parallel_wall" in r:  # the three compiled at once: count the wall time once
        r["compile_sum"] += r["parallel_wall"] - sum(r[k + "_compile"] for k in ("init", "epoch", "eval"))
    return r


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--out", default="benchmarks/results/compile_time.jsonl", help="'' writes no record")
    a = ap.parse_args()
    got = {c: [] for c in a.cases}
    for r in range(a.repeats):
        for c in a.cases:
            got[c].append(run_case(*CASES[c]))
            print(f"round {r + 1} {c}: compile {got[c][-1]['compile_sum']:.2f} s", flush=True)
    med = {c: {k: statistics.median(x[k] for x in v) for k in STAGES} for c, v in got.items()}
    base = med.get("xla_defaults")  # (the ratio column needs that case)
    print(f"\nmedian of {a.repeats}, s (fresh process, no compilation cache); {os.cpu_count()} cpus")
    print(f"{'case':>20} " + " ".join(f"{k:>13}" for k in STAGES) + "  compile x xla_defaults")
    for c, m in med.items():
        ratio = f"{m['compile_sum'] / base['compile_sum']:.2f}" if base else "-"
        print(f"{c:>20} " + " ".join(f"{m[k]:13.3f}" for k in STAGES) + f"  {ratio:>6}")
    if a.out:
        with open(a.out, "a") as fh:
            fh.write(json.dumps({"time": time.strftime("%Y-%m-%d %H:%M"), "cases": got}) + "\n")


if __name__ == "__main__":
    main()
