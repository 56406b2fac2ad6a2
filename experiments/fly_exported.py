"""Fly an exported policy outside JAX: a NumPy re-implementation of the evaluation protocol
from what ``policy.json`` says, for users who put the policy in their own simulator or on a
vehicle.  It imports nothing from ``ttd3_jax``: only NumPy, onnxruntime (``pip install -e
".[export]"``), the export's ``policy.json`` / ``policy.onnx`` and the protocol tracks in
``experiments/tracks/protocol/`` (``t,x,y,z`` at every physics step).

It builds every observation part of the ``fast``, ``fast_dpg``, ``paper`` and ``robust``
presets from ``policy.json`` (:func:`observe`, :class:`Memory`): p, v, q, p_ahead,
p_ahead_error, error, omega (body rates), the memory parts last_action and error_integral,
the preview of the reference (``preview_s``) and the reference integral's shift; and it
simulates the ``instant`` and ``first_order`` rate models of the nominal vehicle.  A policy
that reads anything else (a vehicle descriptor) or flies another rate model is refused,
naming it.  Prints Σ‖e‖ per track against ``expected_tracking_error``.
``experiments/transfer_crazyflow.py`` builds its observation with the same functions.

    python -m ttd3_jax.export RUN_DIR --out POLICY_DIR
    python experiments/fly_exported.py POLICY_DIR                          # Spiral-RT, LOS-RT
    python experiments/fly_exported.py POLICY_DIR --tracks validation_00 validation_01
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

TRACKS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "tracks", "protocol")
# the parts this script builds, and the preview's (``preview_{t:g}s``, one per time of preview_s)
PARTS = ("p", "v", "q", "p_ahead", "p_ahead_error", "error", "omega", "last_action", "error_integral",
         "action_history")  # fmt: skip
PREVIEW = "preview_"
RATE_MODELS = ("instant", "first_order")


def check_observation(meta: dict) -> str | None:
    """Why :func:`observe` cannot build the observation of ``meta`` (None: it can)."""
    spec = meta["observation_spec"]
    preview = {f"{PREVIEW}{t:g}s" for t in spec.get("preview_s", [])}
    read = [part for part in spec["parts"] if not part.get("critic_only", False)]
    other = [part["name"] for part in read if part["name"] not in PARTS and part["name"] not in preview]
    if other:
        allowed = [*PARTS, *(sorted(preview) or [f"{PREVIEW}<t>s"])]
        return f"its observation has parts this script does not build: {other}; allowed: {allowed}"
    if not spec["frame"].startswith("track") and not spec["frame"].startswith("world"):
        return f"observation frame {spec['frame']!r}; allowed: track, world"
    if sum(part["size"] for part in read) != meta["obs_size"]:
        return f"its parts hold {sum(p['size'] for p in read)} entries, obs_size is {meta['obs_size']}"
    return None


def check(meta: dict) -> str | None:
    """Why this script cannot fly the policy of ``meta`` (None: it can)."""
    why = check_observation(meta)
    if why is None and meta["rate_model"]["name"] not in RATE_MODELS:
        why = f"rate model {meta['rate_model']['name']!r}; allowed: {list(RATE_MODELS)}"
    return why


def action_to_control(meta: dict, a: np.ndarray) -> tuple[float, np.ndarray]:
    """policy.json's ``action_map``: thrust (N) and commanded body rates (rad/s)."""
    t, r = meta["action_map"]["thrust_N"], meta["action_map"]["body_rates_rad_s"]
    a0 = float(a[0])
    thrust = t["hover"] + a0 * ((t["max"] - t["hover"]) if a0 >= 0 else (t["hover"] - t["min"]))
    lo, hi = np.asarray(r["min"]), np.asarray(r["max"])
    return thrust, lo + (a[1:].astype(np.float64) + 1.0) / 2.0 * (hi - lo)


def derivative(meta: dict, x: np.ndarray, c, w_cmd: np.ndarray) -> np.ndarray:
    """ẋ of x = (p, v, q, ω) under policy.json's ``dynamics``: c the collective acceleration."""
    veh, f = meta["vehicle"], x.dtype.type
    v, q, w = x[3:6], x[6:10], x[10:13]
    qw, qx, qy, qz = q
    body_z = np.array(
        [2 * (qx * qz + qw * qy), 2 * (qy * qz - qw * qx), 1 - 2 * (qx * qx + qy * qy)], x.dtype
    )
    v_dot = c * body_z - np.array([0.0, 0.0, veh["gravity"]], x.dtype)
    instant = meta["rate_model"]["name"] == "instant"
    wx, wy, wz = w_cmd.astype(x.dtype) if instant else w
    omega = np.array([[0, -wx, -wy, -wz], [wx, 0, wz, -wy], [wy, -wz, 0, wx], [wz, wy, -wx, 0]], x.dtype)
    w_dot = np.zeros(3, x.dtype) if instant else (w_cmd.astype(x.dtype) - w) / f(veh["tau_rate"])
    return np.concatenate([v, v_dot, f(0.5) * (omega @ q), w_dot]).astype(x.dtype)


def rk4(meta: dict, x: np.ndarray, c, w_cmd: np.ndarray) -> np.ndarray:
    """One physics step (RK4, then q back to unit norm; ``instant``: ω = the command)."""
    f = x.dtype.type
    h, c = f(meta["evaluation_protocol"]["physics_dt_s"]), f(c)
    k1 = derivative(meta, x, c, w_cmd)
    k2 = derivative(meta, x + h / 2 * k1, c, w_cmd)
    k3 = derivative(meta, x + h / 2 * k2, c, w_cmd)
    k4 = derivative(meta, x + h * k3, c, w_cmd)
    x = (x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)).astype(x.dtype)
    x[6:10] /= np.sqrt(np.sum(x[6:10] ** 2))
    if meta["rate_model"]["name"] == "instant":
        x[10:13] = w_cmd
    return x


class Memory:
    """What the observation keeps from step to step (``observation_spec.memory``): the last
    action (4), the leaky error integral (3, m s) and the reference integral (3, m s), all
    zero at the start of a flight.  ``dtype``: the precision it is kept in (the env's float32)."""

    def __init__(self, meta: dict, dtype=np.float32):
        self.spec = meta["observation_spec"].get("memory") or {}
        self.integral = self.spec.get("reference_integral") or {}
        self.last_action = np.zeros(4, dtype)
        self.error_integral = np.zeros(3, dtype)
        self.ref_int = np.zeros(3, dtype)
        self.keep = np.asarray(self.spec.get("action_history_keep", []), dtype)[:, None]
        self.action_history = np.zeros((len(self.keep), 4), dtype)

    def update(self, action: np.ndarray, p: np.ndarray, p_d: np.ndarray) -> None:
        """After a control step: ``action`` the one it applied (clipped to [-1, 1]), ``p`` the
        measured position (m) and ``p_d`` the reference at the step's end."""
        f = self.error_integral.dtype.type
        self.last_action = np.clip(action, -1.0, 1.0).astype(self.last_action.dtype)
        f1 = self.keep.dtype.type(1)
        self.action_history = self.keep * self.action_history + (f1 - self.keep) * self.last_action
        if not self.spec:
            return
        e = np.asarray(p_d, self.error_integral.dtype) - np.asarray(p, self.error_integral.dtype)
        dt = f(self.spec["dt_s"])
        self.error_integral = f(self.spec["leak"]) * self.error_integral + dt * e
        if self.integral:  # only within the band: no wind-up far off the track
            self.ref_int = self.ref_int + dt * np.where(np.abs(e) < f(self.integral["band_m"]), e, f(0))

    def shift(self) -> np.ndarray:
        """s (3,) m: the reference integral's shift of the observed reference (0 without one)."""
        if not self.integral:
            return np.zeros(3, self.ref_int.dtype)
        lim = self.ref_int.dtype.type(self.integral["limit_m"])
        return np.clip(self.ref_int.dtype.type(self.integral["gain_per_s"]) * self.ref_int, -lim, lim)


def reference(ref: np.ndarray, k: int) -> np.ndarray:
    """p_d at physics step k (m); past the table's end, its last point (held)."""
    return ref[min(k, len(ref) - 1)]


def observe(meta: dict, x: np.ndarray, ref: np.ndarray, k: int, memory: Memory | None = None) -> np.ndarray:
    """The observation at physics step k, part by part as ``observation_spec`` lists them: ``x``
    = (p, v, q (qw, qx, qy, qz), ω) of the vehicle as measured, ``ref`` (rows, 3) the reference
    at every physics step, ``memory`` the parts kept from step to step (needed when read)."""
    spec = meta["observation_spec"]
    memory = memory or Memory(meta, x.dtype)
    p, v, q, w = x[0:3] - memory.shift().astype(x.dtype), x[3:6], x[6:10], x[10:13]
    q = -q if q[0] < 0 and "qw >= 0" in spec["quaternion_sign"] else q
    origin = reference(ref, k) if spec["frame"].startswith("track") else np.zeros(3, x.dtype)
    look = spec["lookahead_physics_steps"]
    ahead = reference(ref, k + look)
    p_err = reference(ref, k + 1) if "k+1" in spec["error_reference"] else reference(ref, k)
    parts = {"p": p - origin, "v": v, "q": q, "p_ahead": ahead - origin, "p_ahead_error": ahead - p,
             "error": [np.linalg.norm(p_err - p)], "omega": w, "last_action": memory.last_action,
             "error_integral": memory.error_integral,
             "action_history": memory.action_history.ravel()}  # fmt: skip
    dt = meta["evaluation_protocol"]["physics_dt_s"]
    for t in spec.get("preview_s", []):  # the reference t s after p_ahead, relative to it
        parts[f"{PREVIEW}{t:g}s"] = reference(ref, k + look + round(t / dt)) - ahead
    read = [part["name"] for part in spec["parts"] if not part.get("critic_only", False)]
    return np.concatenate([np.asarray(parts[name], x.dtype) for name in read])


def fly(meta: dict, session, ref: np.ndarray, dtype=np.float32) -> dict:
    """One protocol episode on ``ref`` (rows, 3): Σ‖e‖ over physics steps 1…N and the crash flag."""
    proto, veh = meta["evaluation_protocol"], meta["vehicle"]
    ref = ref.astype(dtype)
    x = np.zeros(13, dtype)
    x[0:3], x[6] = ref[0], 1.0  # at rest on p_d(0), level
    newton = veh.get("thrust_units", "newton") == "newton"
    errors = np.zeros(proto["physics_steps"], dtype)
    memory, a = Memory(meta, dtype), np.zeros(4, np.float32)
    for k in range(proto["physics_steps"]):
        if k % meta["action_repeat"] == 0:
            if k > 0:  # the control step that ended here: the memory parts
                memory.update(a, x[0:3], ref[k])
            obs = observe(meta, x, ref, k, memory)[None].astype(np.float32)
            a = np.clip(session.run(["action"], {"obs": obs})[0][0], -1.0, 1.0)
            thrust, w_cmd = action_to_control(meta, a)
            c = thrust / veh["mass"] if newton else thrust
        x = rk4(meta, x, c, w_cmd)
        errors[k] = np.linalg.norm(x[0:3] - ref[k + 1])
    return {"tracking_error": float(np.sum(errors, dtype=dtype)), "crashed": bool(np.any(errors > 1.0))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python experiments/fly_exported.py", description=__doc__.split("\n\n")[0]
    )
    ap.add_argument("policy_dir", help="a directory written by python -m ttd3_jax.export")
    ap.add_argument("--tracks", nargs="+", default=["spiral_rt", "los_rt_seed00"],
                    help=f"names of CSV files in {TRACKS} (without .csv); 'validation': every "
                    "validation_*.csv there and their mean (the files hold the fast preset's bank; "
                    "protocol_tracks.py --validation-preset P --out DIR writes P's)")  # fmt: skip
    ap.add_argument("--tracks-dir", default=TRACKS)
    a = ap.parse_args(argv)
    if "validation" in a.tracks and os.path.isdir(a.tracks_dir):
        bank = sorted(
            n[:-4] for n in os.listdir(a.tracks_dir) if n.startswith("validation_") and n.endswith(".csv")
        )
        a.tracks = [t for t in a.tracks if t != "validation"] + bank
    paths = [os.path.join(a.policy_dir, n) for n in ("policy.json", "policy.onnx")]
    missing = [p for p in paths if not os.path.isfile(p)]
    missing += [os.path.join(a.tracks_dir, f"{t}.csv") for t in a.tracks
                if not os.path.isfile(os.path.join(a.tracks_dir, f"{t}.csv"))]  # fmt: skip
    if missing:
        print(f"error: no such file: {missing[0]} (a policy directory holds policy.json and policy.onnx; "
              f"tracks are CSV names in {a.tracks_dir})", file=sys.stderr)  # fmt: skip
        return 2
    meta = json.load(open(paths[0]))
    why = check(meta)
    if why:
        print(f"error: {a.policy_dir}: {why}", file=sys.stderr)
        return 2
    import onnxruntime as ort

    session = ort.InferenceSession(paths[1], providers=["CPUExecutionProvider"])
    expected = meta.get("expected_tracking_error", {}).get("sum_norm_e_m", {})
    print(f"{'track':>16} {'Σ‖e‖ (m)':>12} {'expected':>12} {'rel. diff':>10} crashed")
    val = []
    for name in a.tracks:
        ref = np.loadtxt(os.path.join(a.tracks_dir, f"{name}.csv"), delimiter=",", skiprows=1)[:, 1:4]
        r = fly(meta, session, ref)
        val += [r["tracking_error"]] if name.startswith("validation_") else []
        row(name, r["tracking_error"], expected.get(name), r["crashed"])
    if val:
        row(
            "validation_mean",
            float(np.mean(np.asarray(val, np.float32))),
            expected.get("validation_mean"),
            "",
        )
    return 0


def row(name: str, got: float, want: float | None, crashed) -> None:
    """One line of the table: Σ‖e‖, the export's expected value and their relative difference."""
    rel = f"{(got - want) / want:10.1e}" if want else f"{'-':>10}"
    print(f"{name:>16} {got:12.6f} {f'{want:.6f}' if want else '-':>12} {rel} {crashed}")


if __name__ == "__main__":
    sys.exit(main())
