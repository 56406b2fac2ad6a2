"""``python -m ttd3_jax.export``: a trained quadrotor policy as ``policy.onnx``, a C header
``policy.h`` and a ``policy.json`` sidecar (see :mod:`ttd3_jax.interop.policy`).

    python -m ttd3_jax.export RUN_DIR --out DIR            # the run's newest checkpoint
    python -m ttd3_jax.export RUN_DIR --best --out DIR     # the policy selected on validation
    python -m ttd3_jax.export RUN_DIR --epoch 3 --seed-index 1 --out DIR --force
"""

from __future__ import annotations

import argparse
import logging
import os
import sys

from ttd3_jax.checks import writable_dir
from ttd3_jax.cli.console import show_messages
from ttd3_jax.interop import policy as pe
from ttd3_jax.run import rundir
from ttd3_jax.sim import observation


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m ttd3_jax.export", description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "run_dir", help="a quadrotor training run (or a training --out directory: its newest run)"
    )
    ap.add_argument("--out", required=True, help="directory for policy.onnx, policy.h and policy.json")
    ap.add_argument("--best", action="store_true", help="the policy selected on the validation tracks")
    ap.add_argument("--epoch", type=int, default=None, help="this checkpoint (default: the newest)")
    ap.add_argument("--seed-index", type=int, default=0, help="which seed of a multi-seed run (from 0)")
    ap.add_argument("--no-onnx", action="store_true", help="only policy.h and policy.json (no onnx needed)")
    ap.add_argument("--force", action="store_true", help="overwrite the policy files already in --out")
    return ap


def check_args(ap: argparse.ArgumentParser, args) -> None:
    """Refuse bad input before anything loads."""
    if args.best and args.epoch is not None:
        ap.error("--best and --epoch exclude each other")
    if args.epoch is not None and args.epoch < 0:
        ap.error(f"--epoch must be >= 0, got {args.epoch}")
    try:
        writable_dir("--out", args.out)
        rundir.refuse_run_files("--out", args.out, folder=True)
    except ValueError as e:
        ap.error(str(e))
    there = [f for f in pe.FILES if os.path.exists(os.path.join(args.out, f))]
    if there and not args.force:
        ap.error(f"--out {args.out!r} already holds {there}; pass --force to overwrite them")
    if not args.no_onnx:
        try:
            import onnx  # noqa: F401
        except ImportError:
            ap.error('policy.onnx needs the onnx package: pip install -e ".[export]" (or pass --no-onnx)')


def main(argv: list[str] | None = None) -> int:
    logging.getLogger("absl").setLevel(logging.ERROR)
    show_messages()  # the package's notes (a damaged file), as plain lines
    ap = build_parser()
    args = ap.parse_args(argv)
    check_args(ap, args)
    try:
        run_dir, note = rundir.find_run(args.run_dir)
        if note:
            print(note)
        run = rundir.load_run(run_dir, args.epoch, best=args.best)
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if not 0 <= args.seed_index < len(run.thetas):
        print(
            f"error: --seed-index {args.seed_index}: the run has seeds 0..{len(run.thetas) - 1}",
            file=sys.stderr,
        )
        return 2
    cfg = run.env_config
    o = cfg.observation
    if o.obs_privileged:
        print(f"error: {run_dir} observes obs_privileged=True; export supports the actor's observation "
              "without the critics' parts only (obs_privileged false)", file=sys.stderr)  # fmt: skip
        return 2
    seed, (actor, stats) = run.thetas[args.seed_index]
    obs_size = observation.layout(run.env_config).size  # the env's, without reading its training tracks
    policy = pe.from_params(actor, stats, obs_size)
    try:
        meta = pe.sidecar(run_dir, run, seed, args.best, obs_size)
        written = pe.write(args.out, policy, meta, onnx=not args.no_onnx)
    except ValueError as e:  # non-finite weights, an observation part policy.h cannot build
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"error: --out {args.out!r}: cannot write the policy files ({e.strerror})", file=sys.stderr)
        return 1
    print(f"wrote {', '.join(written)} to {args.out} (run {meta['source']['run']}, seed {seed}, "
          f"epoch {meta['source']['epoch']}, {meta['control_hz']:g} Hz)")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
