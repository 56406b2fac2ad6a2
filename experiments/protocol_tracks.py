"""The evaluation protocol's tracks as CSV files, for users who fly a policy outside JAX.

Writes ``experiments/tracks/protocol/``: ``spiral_rt.csv``, ``los_rt_seed00.csv`` …
``los_rt_seed20.csv`` (LOS-RT seed 0 is the paper's test track, seeds 1-20 the multi-track
test) and ``validation_00.csv`` … ``validation_09.csv`` (the tracks that select a policy of the
default ``fast`` preset).  Each holds ``t,x,y,z``: the reference position p_d(k) (m, world
frame, z up) at every physics step (t = k · 1 ms).  The test tracks run k = 0 … 5101: the 3000
evaluated steps, a look-ahead of up to 100 steps and the farthest reference preview an
observation may show after it (``PREVIEW_MAX_S`` = 2 s; ``--preset robust`` reads 1 s), the
same for every preset.  The validation tracks run over their env's table (``horizon_steps``
rows).  Their random-acceleration tracks depend on that table's size (its segment count), so a
preset whose look-ahead, preview or critic inputs differ selects on other tracks than
``fast``'s (docs/paper-notes.md, "Validation tracks"): ``--validation-preset NAME`` writes that
preset's bank (``robust``: the wide mixture's 18) instead.  LOS-RT and the
validation tracks are drawn with JAX's Threefry PRNG, so outside JAX these files are the only
way to rebuild them.  Values are float32, written with 9
significant digits (they read back exactly).

    python experiments/protocol_tracks.py            # (re)write the files
    python experiments/protocol_tracks.py --check    # compare the files with the generator
    python experiments/protocol_tracks.py --validation-preset robust --out DIR   # another bank
"""

from __future__ import annotations

import argparse
import os
import sys

import jax
import numpy as np

from ttd3_jax.run import spec as sp
from ttd3_jax.sim import trajectories as tr
from ttd3_jax.sim.config import PREVIEW_MAX_S, make_config
from ttd3_jax.sim.env import TrackingEnv, num_validation_tracks, validation_tracks

OUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "tracks", "protocol")
MAX_LOOKAHEAD_K = 100  # physics steps
# the last index of EnvConfig.horizon_steps' table: 3000 evaluated steps, the look-ahead, 2 s of preview
LAST_STEP = 3000 + MAX_LOOKAHEAD_K + 2 + round(PREVIEW_MAX_S / 1e-3) - 1
LOS_SEEDS = range(21)
HEADER = "t,x,y,z"


def _config():
    """The evaluation env's config with a table long enough for k = 0 … LAST_STEP."""
    return make_config("paper", lookahead_k=LAST_STEP - make_config("paper").episode_steps)


def _positions(track: tr.Track, dt: float, rows: int = LAST_STEP + 1) -> np.ndarray:
    return np.asarray(tr.reference(track, dt, rows).pos, np.float32)


def validation_bank(preset: str = "fast") -> dict[str, np.ndarray]:
    """``{validation_XX: positions (horizon_steps, 3)}``: the tracks ``preset``'s training
    run selects its policy on, built as its evaluation builds them
    (``control.closed_loop.test_and_validation_metrics``)."""
    cfg = sp.preset(preset).task
    env = TrackingEnv(cfg.for_eval("validation"))
    bank = validation_tracks(cfg, env.num_segments)
    rows = env.config.horizon_steps
    return {f"validation_{i:02d}": _positions(jax.tree.map(lambda x, i=i: x[i], bank), cfg.dt, rows)
            for i in range(num_validation_tracks(cfg))}  # fmt: skip


def protocol_tracks(validation_preset: str = "fast") -> dict[str, np.ndarray]:
    """``{name: positions (rows, 3)}`` as the evaluation's env builds them: the test tracks
    over ``LAST_STEP + 1`` rows, ``validation_preset``'s validation tracks over its table."""
    c = _config()
    out = {"spiral_rt": _positions(TrackingEnv(c.for_eval("spiral_rt")).sample_track(None), c.dt)}
    for s in LOS_SEEDS:
        env = TrackingEnv(c.for_eval("los_rt", los_seed=s))
        out[f"los_rt_seed{s:02d}"] = _positions(env.sample_track(None), c.dt)
    return out | validation_bank(validation_preset)


def to_csv(pos: np.ndarray, dt: float = 1e-3) -> str:
    rows = [f"{k * dt:.3f},{x:.9g},{y:.9g},{z:.9g}" for k, (x, y, z) in enumerate(pos.tolist())]
    return "\n".join([HEADER, *rows]) + "\n"


def read_csv(path: str) -> np.ndarray:
    """``(t, positions)`` of a file this script wrote."""
    data = np.loadtxt(path, delimiter=",", skiprows=1, dtype=np.float64)
    return data[:, 0], data[:, 1:].astype(np.float32)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python experiments/protocol_tracks.py",
                                 description=__doc__.split("\n\n")[0])  # fmt: skip
    ap.add_argument("--out", default=OUT)
    ap.add_argument("--check", action="store_true", help="compare the files in --out with the generator")
    ap.add_argument("--validation-preset", default="fast", choices=[p for p in sp.PRESETS if p != "mujoco"],
                    help="whose validation tracks to write (default: fast, the committed files)")  # fmt: skip
    a = ap.parse_args(argv)
    tracks = protocol_tracks(a.validation_preset)
    if a.check:
        read = {n: read_csv(os.path.join(a.out, f"{n}.csv"))[1] for n in tracks}
        bad = [n for n, p in tracks.items() if not np.array_equal(read[n], p)]
        print(f"{len(tracks) - len(bad)} of {len(tracks)} files equal the generator; differ: {bad or 'none'}")
        return 1 if bad else 0
    os.makedirs(a.out, exist_ok=True)
    for name, pos in tracks.items():
        with open(os.path.join(a.out, f"{name}.csv"), "w") as fh:
            fh.write(to_csv(pos))
    print(f"wrote {len(tracks)} tracks to {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
