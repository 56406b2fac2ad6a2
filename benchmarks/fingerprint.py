"""Bit-level fingerprints of env rollouts and of training, to check a speed change.

A change made for speed should leave every result as it was.  XLA's fusion choices can
move the last bit of a float even where the maths is unchanged, and training is chaotic:
one changed bit anywhere gives a different policy, and every trained figure in docs/ would
then need re-running.  Run this before and after a change and compare the lines:

    python benchmarks/fingerprint.py > /tmp/before.txt     # on the old code
    python benchmarks/fingerprint.py > /tmp/after.txt      # on the new code
    diff /tmp/before.txt /tmp/after.txt                    # empty: bit-identical
    python benchmarks/fingerprint.py --quick               # env parts only (CI smoke run)
    python benchmarks/fingerprint.py --compare benchmarks/results/fingerprint.txt

``benchmarks/results/fingerprint.txt`` holds the lines of the committed code on the
project's 2-core CPU VM without AVX-512, ``fingerprint_avx512.txt`` those on one with it
(XLA:CPU compiles for the instruction set it finds, which moves last bits; its first line
names jax and the CPU; compare like with like: ``grep avx512f /proc/cpuinfo`` tells which).
On an AVX-512 CPU, ``XLA_FLAGS=--xla_cpu_max_isa=AVX2`` gives fingerprint.txt's env lines but
not its train lines (measured on a 2-core AVX2 EPYC VM on 2026-12-05; the capped lines
written before then were wrong there).  ``fingerprint_avx512.txt`` was written on an AVX-512
EPYC; on a 2-core AVX-512 Intel Xeon VM every line matches but ``env_obs_noise``, which reads
``7fff225f8ea838fc`` there both at the file's own commit (468c8ed) and at f73a2b3
(2026-12-05), so that one line differs by CPU vendor, not by code.  Both files were rewritten on
2026-12-07 when :mod:`ttd3_jax.compile_flags` moved every line: ``fingerprint.txt`` holds only
the env lines then (from an AVX-512 EPYC with the AVX2 cap); its train lines need an AVX2 VM.
``fingerprint_avx512.txt``'s ``train_fast`` lines were rewritten again when the ``fast`` preset
moved to 16 envs and 480k transitions (issue 51); every other line was unchanged.
``--compare FILE`` checks each line against FILE and exits 1 naming the ones that differ.

Each line is ``name sha256-prefix``:

  env_*       obs, reward, done, metrics and the carried state of a 64-env x 300-step
              rollout (paper preset with its wind, the practical preset, an eval config)
  train_*     the whole train state after init + one epoch of the ``fast`` / ``fast_dpg``
              presets, run exactly as ``python -m ttd3_jax.train`` runs them
              (``sharding.runner_fns``), and that state's evaluation metrics
  small_*     (``--small``) init + one epoch of small versions of the ``paper`` (T-TD3, and
              TD3 with 3 seeds), ``fast_model_free`` and ``mujoco`` presets: not in the
              reference files; compare the output of two runs
"""

from __future__ import annotations

import argparse
import hashlib
import os
import re
import sys

import jax
import jax.numpy as jnp
import numpy as np

from ttd3_jax.run import sharding
from ttd3_jax.run.report import device_description
from ttd3_jax.run.spec import preset, trainer_for
from ttd3_jax.sim.config import make_config
from ttd3_jax.sim.env import TrackingEnv
from ttd3_jax.td3.trainer import seed_keys


def digest(tree) -> str:
    """sha256 (first 16 hex digits) of every leaf's bytes, in tree order."""
    h = hashlib.sha256()
    for leaf in jax.tree.leaves(tree):
        a = np.asarray(jax.device_get(leaf))
        if jnp.issubdtype(a.dtype, jax.dtypes.prng_key):
            a = np.asarray(jax.random.key_data(leaf))
        h.update(str((a.shape, a.dtype)).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


def env_rollout(cfg, n_envs: int = 64, n_steps: int = 300):
    """Everything a 64-env rollout under fixed pseudo-random actions produces."""
    env = TrackingEnv(cfg)
    s0 = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), n_envs))
    acts = jax.random.uniform(jax.random.PRNGKey(1), (n_steps, n_envs, 4), minval=-1.0, maxval=1.0)

    @jax.jit
    def run(s, acts):
        def body(s, a):
            s = jax.vmap(env.step)(s, a)
            return s, (s.obs, s.reward, s.done, s.metrics, s.info)

        return jax.lax.scan(body, s, acts)

    return run(s0, acts)


def env_cases():
    paper = make_config("paper")
    practical = make_config("practical")
    return {
        "env_paper": paper,
        "env_paper_nowind": paper.replace(wind_sigma=0.0),
        "env_practical": practical,
        "env_practical_fast": practical.replace(hover_centered_thrust=True),
        "env_eval_spiral": practical.for_eval("spiral_rt", wind_sigma=0.5),
        "env_obs_noise": paper.replace(obs_noise_pos=0.01, obs_noise_vel=0.02, obs_noise_quat=0.01),
    }


def train_fingerprint(name: str):
    """``(state digest, eval digest)`` after init and the first epoch, as the CLI runs them."""
    spec = preset(name)
    keys = seed_keys(spec.seed, spec.num_seeds)
    init_fn, epoch_fn, eval_fn, _ = sharding.runner_fns(trainer_for(spec), keys, spec.hp)
    ts = init_fn(keys, spec.hp)
    ts, m = epoch_fn(ts, spec.hp)
    return digest((ts, m)), digest(eval_fn(ts))


def small_specs() -> dict:
    """Every preset at a few epochs' size (``--small``): init + one epoch each, for checking
    a change against presets the reference lines do not cover (compare two runs' output)."""
    paper = dict(total_transitions=2000 + 2 * 50 * 20, warmup_transitions=2000, epochs=2, buffer_size=10000)
    return {
        "small_paper": preset("paper", **paper),
        "small_paper_td3_3seeds": preset("paper", algo="td3", num_seeds=3, **paper),
        "small_fast_model_free": preset(
            "fast_model_free", total_transitions=3584, warmup_transitions=2560, epochs=2, buffer_size=6400
        ),
        "small_mujoco": preset(
            "mujoco", total_transitions=1200, warmup_transitions=1000, epochs=2, buffer_size=5000
        ),  # fmt: skip
    }


def small_fingerprint(spec) -> str:
    keys = seed_keys(spec.seed, spec.num_seeds)
    init_fn, epoch_fn, _, _ = sharding.runner_fns(trainer_for(spec), keys, spec.hp)
    return digest(epoch_fn(init_fn(keys, spec.hp), spec.hp))


def isa() -> str:
    """``", AVX-512"`` where XLA:CPU may use it (its results' last bits differ), else ``""``.

    ``XLA_FLAGS=--xla_cpu_max_isa=AVX2`` caps what XLA compiles for; on an AVX-512 CPU it
    reproduces the env lines of one without it, not the train lines.
    """
    cap = re.search(r"--xla_cpu_max_isa=(\S+)", os.environ.get("XLA_FLAGS", ""))
    if cap and not cap.group(1).upper().startswith("AVX512"):
        return ""
    try:
        with open("/proc/cpuinfo") as fh:
            return ", AVX-512" if " avx512f" in fh.read() else ""
    except OSError:
        return ""


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="env rollouts only")
    ap.add_argument("--train", nargs="*", default=["fast", "fast_dpg"], help="training presets to run")
    ap.add_argument("--compare", default=None, help="reference file of lines (see above)")
    ap.add_argument("--small", action="store_true", help="also init + one epoch of every preset, small")
    args = ap.parse_args(argv)
    want, header = {}, f"# jax {jax.__version__}, {device_description()}{isa()}"
    if args.compare:
        with open(args.compare) as fh:
            lines = [line.strip() for line in fh if line.strip()]
        want = dict(line.split() for line in lines if not line.startswith("#"))
        theirs = next((line for line in lines if line.startswith("#")), "")
        if theirs != header:  # another jax or CPU may round differently
            print(f"# warning: {args.compare} was made on another machine or jax: {theirs!r}")
    print(header)
    got = {}
    for name, cfg in env_cases().items():
        got[name] = digest(env_rollout(cfg))
        print(name, got[name], flush=True)
    if not args.quick:
        for name in args.train:
            got[f"train_{name}"], got[f"train_{name}_eval"] = train_fingerprint(name)
            print(f"train_{name}", got[f"train_{name}"], flush=True)
            print(f"train_{name}_eval", got[f"train_{name}_eval"], flush=True)
    for name, spec in (small_specs() if args.small else {}).items():
        got[name] = small_fingerprint(spec)
        print(name, got[name], flush=True)
    if args.compare:
        differ = sorted(k for k in got if k in want and got[k] != want[k])
        print(f"{len(differ)} of {sum(k in want for k in got)} lines differ from {args.compare}", *differ)
        return 1 if differ else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
