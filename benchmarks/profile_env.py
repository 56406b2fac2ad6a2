"""Where an env step's time goes on CPU: per-kernel times of one compiled scan.

Runs one case of ``env_throughput.py`` under ``jax.profiler`` with XLA:CPU's per-kernel
trace events switched on, and prints each kernel's time per env step, largest first. The
profiler adds about 2 µs per kernel, so read the ranking and the shares, not the sum.

    python benchmarks/profile_env.py                      # env_nominal, 1024 envs
    python benchmarks/profile_env.py --case rk4 --top 8
    python benchmarks/profile_env.py --quick              # smoke run (CI)
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
import env_throughput as et  # noqa: E402

from ttd3_jax.sim.config import make_config  # noqa: E402

CASES = ("rk4", "env_nominal", "env_paper")
# opcodes worth naming when saying what a kernel does (elementwise arithmetic is implied)
NOTABLE = (
    "gather",
    "concatenate",
    "reduce",
    "sine",
    "cosine",
    "sqrt",
    "rsqrt",
    "is-finite",
    "erf-inv",
    "xor",
)


def kernel_contents(hlo: str) -> dict[str, str]:
    """For each fusion in the optimised HLO text, the notable opcodes it contains."""
    bodies = dict(re.findall(r"\n(%[\w.\-]+) [^\n]*\{\n(.*?)\n\}", hlo, re.S))
    out = {}
    for name, comp in re.findall(r"(%[\w.\-]+) = [^\n]* fusion\([^\n]*calls=(%[\w.\-]+)", hlo):
        ops = re.findall(r"= \S+ ([a-z\-]+)\(", bodies.get(comp, ""))
        out[name[1:]] = ", ".join(sorted({op for op in ops if op in NOTABLE}))
    return out


def kernel_times(fn, x0, n_steps: int) -> dict[str, float]:
    """``{kernel: (µs per scan step, notable opcodes inside)}`` for each XLA kernel."""
    compiled = jax.jit(fn).lower(x0).compile()
    contents = kernel_contents(compiled.as_text())
    jax.block_until_ready(compiled(x0))
    with tempfile.TemporaryDirectory() as d:
        jax.profiler.start_trace(d, create_perfetto_trace=True)
        jax.block_until_ready(compiled(x0))
        jax.profiler.stop_trace()
        (path,) = glob.glob(os.path.join(d, "**", "perfetto_trace.json.gz"), recursive=True)
        events = json.load(gzip.open(path))
    events = events["traceEvents"] if isinstance(events, dict) else events
    total, count = collections.Counter(), collections.Counter()
    for e in events:
        if e.get("ph") == "X":
            total[e["name"]] += e["dur"]
            count[e["name"]] += 1

    # kernels run once per step; skip the executor's own spans and the "end:" markers
    def kernel(name):
        return count[name] == n_steps and "::" not in name and not name.startswith(("end:", "$"))

    return {name: (total[name] / n_steps, contents.get(name, "")) for name in total if kernel(name)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", default="env_nominal", choices=CASES)
    ap.add_argument("--envs", type=int, default=1024)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--top", type=int, default=15)
    ap.add_argument("--quick", action="store_true", help="tiny sizes, to keep the script alive in CI")
    args = ap.parse_args(argv)
    if args.quick:
        args.envs, args.steps = 16, 10
    if min(args.envs, args.steps, args.top) < 1:
        ap.error("--envs, --steps and --top must be >= 1")

    base = make_config("paper")
    nominal = base.replace(wind_sigma=0.0)
    fn, x0 = {
        "rk4": lambda: et.rk4_case(base, args.envs, args.steps),
        "env_nominal": lambda: et.env_case(nominal, args.envs, args.steps),
        "env_paper": lambda: et.env_case(base, args.envs, args.steps),
    }[args.case]()
    times = kernel_times(fn, x0, args.steps)
    if not times:
        sys.exit("no per-kernel trace events: this jax/XLA does not emit them on this device")
    total = sum(us for us, _ in times.values())
    print(f"case={args.case} envs={args.envs} steps={args.steps} device={jax.devices()[0].platform}")
    print(f"{'kernel':<32} {'us/step':>8} {'share':>6}  contains")
    for name, (us, what) in sorted(times.items(), key=lambda kv: -kv[1][0])[: args.top]:
        print(f"{name[:32]:<32} {us:>8.2f} {us / total:>6.1%}  {what}")
    print(f"{len(times)} kernels, {total:.1f} us/step in all (profiled)")
    return times


if __name__ == "__main__":
    main()
