"""Rewrite a run's ``config.json`` in the current format, for the long runs pinned at an
older commit (experiments/paper_budget.sh and mujoco_budget.sh run 7c6bdf6, which writes
format 14).  ttd3_jax reads only its own format and keeps no migration code; the steps
here are the formats' own changes since 14:

- 15 added ``train.selection`` (``"validation"``: the behaviour before it existed), and on a
  side branch ``task.observation.disturbance_tau`` (0: off);
- 16 holds ``selection`` and not ``disturbance_tau`` (a run that set it is refused).

The rewritten file must load (``ttd3_jax.run.spec.from_dict``), or nothing is written.

    python experiments/current_format.py RUN_DIR/config.json [...]
"""

from __future__ import annotations

import json
import sys

from ttd3_jax.run import spec as sp


def rewrite(d: dict) -> dict:
    """``d`` (format 14, 15 or current) in the current format; ValueError for another."""
    d = json.loads(json.dumps(d))
    fmt = d.get("format")
    if fmt == sp.CONFIG_FORMAT:
        return d
    if fmt not in (14, 15):
        raise ValueError(f"config format {fmt!r}: this script rewrites formats 14 and 15 only")
    d["train"].setdefault("selection", "validation")
    if d["task"]["observation"].pop("disturbance_tau", 0.0):
        raise ValueError("observation.disturbance_tau is set: a run of a removed option")
    d["format"] = sp.CONFIG_FORMAT
    sp.from_dict(d)  # raises if it does not load
    return d


def main(paths: list[str]) -> int:
    for path in paths:
        with open(path) as fh:
            d = rewrite(json.load(fh))
        with open(path, "w") as fh:
            json.dump(d, fh, indent=2)
            fh.write("\n")
        print(f"{path}: format {d['format']}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
