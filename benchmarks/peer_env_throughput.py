"""Env-step throughput against a peer simulator (crazyflow) and the bare RK4 model, in one run.

Our cases are those of ``env_throughput.py``: a jitted ``lax.scan`` of T steps over N
vmapped vehicles.  crazyflow (a JAX + MuJoCo quadrotor simulator) runs in its own venv
(crazyflow 0.4.0 excludes jax 0.10.2) as a worker process of this script (see
``_peers.py``).  Every case is compiled first (compile time reported apart), then all cases
of one env count are timed interleaved, best of ``--repeats``.

    python benchmarks/peer_env_throughput.py            # 1, 1024 and 16384 envs
    python benchmarks/peer_env_throughput.py --quick    # 1 and 64 envs, few steps (CI)

Ours (this interpreter):
  rk4            bare model: vmapped rk4_step, fixed controls (the floor)
  env_nominal    env.step (training tracks, no wind, no observation noise), 1 kHz RK4,
                 thrust + body-rate action with the paper's "instant" rate model
  env_torque     the same with the "torque" rate model (body-rate loop + rigid-body
                 rotation, closer to crazyflow's first-principles model)
  env_nominal@cf env_nominal run inside the crazyflow worker (its jax), as a cross-check
crazyflow (worker; 1 kHz sim, RK4 integrator, controllers at 1 kHz):
  cf_rate_stepn  body-rate control, first-principles dynamics: its own jitted ``Sim.step``
                 pipeline with ``n_steps=T`` (one call, an internal scan; command fixed).
                 The fastest way crazyflow offers.
  cf_rate_scan   the same pipeline's pure step (``sim._step``, ``n_steps=1``) and
                 ``functional.body_rate_control`` inside our own ``lax.scan``: a command
                 set every step, like an RL env step
  cf_rate_loop   the object API as its README uses it: a Python loop of
                 ``sim.body_rate_control(cmd); sim.step(1)`` (at most 200 steps timed)
  cf_att_stepn   attitude control, fitted ``so_rpy`` dynamics (crazyflow's cheapest model),
                 ``Sim.step(T)``
  cf_att_scan    the same, scanned with a command every step
"""

from __future__ import annotations

import argparse
import os
import sys

import _peers

# env counts and steps per timed call: (envs, steps)
SIZES = [(1, 2000), (1024, 1000), (16384, 100)]
QUICK_SIZES = [(1, 100), (64, 50)]
LOOP_STEPS = 200  # most Python-loop steps timed per call


# --------------------------------------------------------------------------- ours


def _compile(fn, x0):
    import time

    import jax

    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(x0).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(x0))  # warm-up
    return (lambda: jax.block_until_ready(compiled(x0))), compile_s


def build_ours(case: str, envs: int, steps: int):
    import jax
    from env_throughput import env_case, rk4_case

    from ttd3_jax.sim.config import make_config
    from ttd3_jax.sim.dynamics import QuadParams

    base = make_config("paper")
    nominal = base.replace(wind_sigma=0.0)
    if case == "rk4":
        fn, x0 = rk4_case(base, envs, steps)
    elif case == "env_nominal":
        fn, x0 = env_case(nominal, envs, steps)
    elif case == "env_torque":
        cfg = nominal.replace(quad=QuadParams.create(rate_model="torque"))
        fn, x0 = env_case(cfg, envs, steps)
    else:
        raise ValueError(case)
    run, compile_s = _compile(fn, x0)
    return run, dict(compile_s=compile_s, env_steps=envs * steps, jax=jax.__version__)


# --------------------------------------------------------------------------- crazyflow


def build_crazyflow(case: str, envs: int, steps: int):
    import time

    import crazyflow  # noqa: F401  (sets SCIPY_ARRAY_API before scipy is imported)
    import crazyflow.sim.functional as F
    import jax
    import jax.numpy as jnp
    import numpy as np
    from crazyflow import Control, Dynamics, Sim
    from crazyflow.sim.integration import Integrator

    control, mode = case.removeprefix("cf_").split("_")
    rate = control == "rate"
    t0 = time.perf_counter()
    sim = Sim(
        n_worlds=envs,
        n_drones=1,
        dynamics=Dynamics.first_principles if rate else Dynamics.so_rpy,
        control=Control.body_rate if rate else Control.attitude,
        integrator=Integrator.rk4,
        freq=1000,
        attitude_freq=1000,
        body_rate_freq=1000,
        force_torque_freq=1000,
        device="cpu",
    )
    setup_s = time.perf_counter() - t0
    # start 1 m up, flying (not resting on the floor clip); hover thrust +- small commands
    sim.data = sim.data.replace(states=sim.data.states.replace(pos=sim.data.states.pos.at[..., 2].set(1.0)))
    mass = float(np.asarray(sim.data.params.mass).ravel()[0])
    rng = np.random.default_rng(1)
    cmd = np.zeros((envs, 1, 4), np.float32)
    cmd[..., :3] = rng.uniform(-0.05, 0.05, (envs, 1, 3))
    cmd[..., 3] = mass * 9.81
    cmd = jnp.asarray(cmd)
    set_cmd = F.body_rate_control if rate else F.attitude_control
    data0 = set_cmd(sim.data, cmd)
    step = sim._step  # what Sim.step calls: jit(scan(pipeline), static n_steps)

    if mode == "stepn":
        t0 = time.perf_counter()
        compiled = step.lower(data0, n_steps=steps).compile()
        compile_s = time.perf_counter() - t0
        jax.block_until_ready(compiled(data0))
        run = lambda: jax.block_until_ready(compiled(data0))
        n = envs * steps
    elif mode == "scan":

        def scanned(data):
            def body(d, _):
                return step(set_cmd(d, cmd), n_steps=1), None

            d, _ = jax.lax.scan(body, data, None, length=steps)
            return d.states.pos.sum()

        run, compile_s = _compile(scanned, data0)
        n = envs * steps
    elif mode == "loop":
        loop_steps = min(steps, LOOP_STEPS)
        sim.data = data0
        setter = sim.body_rate_control if rate else sim.attitude_control

        def run():
            for _ in range(loop_steps):
                setter(cmd)
                sim.step(1)
            jax.block_until_ready(sim.data)

        t0 = time.perf_counter()
        setter(cmd)
        sim.step(1)
        jax.block_until_ready(sim.data)
        compile_s = time.perf_counter() - t0  # first call: tracing + compilation
        run()
        n = envs * loop_steps
    else:
        raise ValueError(case)
    return run, dict(compile_s=compile_s, setup_s=setup_s, env_steps=n, jax=jax.__version__)


def build(case: str, envs: int, steps: int):
    if case.startswith("cf_"):
        return build_crazyflow(case, envs, steps)
    return build_ours(case.removesuffix("@cf"), envs, steps)


BUILDERS = {"env": build}
OURS = ("rk4", "env_nominal", "env_torque")
CF_RATE = ("cf_rate_stepn", "cf_rate_scan", "cf_rate_loop")
CF_ATT = ("cf_att_stepn", "cf_att_scan")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="1 and 64 envs, few steps (CI)")
    ap.add_argument("--no-peer", action="store_true", help="our cases only")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--out", default="benchmarks/results/peer_env_throughput.jsonl")
    args = ap.parse_args(argv)
    if args.worker:
        # crazyflow needs scipy's array API mode, set before anything (ttd3_jax too) imports scipy
        os.environ.setdefault("SCIPY_ARRAY_API", "1")
        return _peers.serve(BUILDERS)
    if args.repeats < 1:
        ap.error(f"--repeats must be >= 1, got {args.repeats}")
    if args.quick:
        args.repeats = 1
    sizes = QUICK_SIZES if args.quick else SIZES

    record = _peers.machine_record(argv)
    local = _peers.Local(BUILDERS)
    worker, cf_versions = None, {}
    if not args.no_peer:
        py = _peers.find_python("crazyflow")
        if py is None:
            print(_peers.missing("crazyflow"))
        else:
            worker = _peers.Worker(py, os.path.abspath(__file__), "crazyflow")
            cf_versions = worker.versions(["crazyflow", "jax", "jaxlib", "mujoco", "ttd3_jax"])
            print(f"crazyflow worker: {py} {cf_versions}")

    names = list(OURS) + (["env_nominal@cf", *CF_RATE, *CF_ATT] if worker else [])
    rows = []
    try:
        for envs, steps in sizes:
            built = {}
            for name in names:
                backend = worker if (name.startswith("cf_") or name.endswith("@cf")) else local
                try:
                    built[name] = (
                        backend,
                        backend.build(f"{name}/{envs}", "env", case=name, envs=envs, steps=steps),
                    )
                except RuntimeError as e:  # a peer case that cannot be built is reported, not fatal
                    print(f"[{name} @ {envs} envs] build failed: {str(e).splitlines()[0]}", file=sys.stderr)
            best = {name: float("inf") for name in built}
            for _ in range(args.repeats):
                for name, (backend, _) in built.items():
                    best[name] = min(best[name], backend.time(f"{name}/{envs}"))
            for name, (backend, _) in built.items():
                backend.forget(f"{name}/{envs}")
            cf_best = max(
                (built[n][1]["env_steps"] / best[n] for n in ("cf_rate_stepn", "cf_rate_scan") if n in built),
                default=None,
            )
            rk4_sps = built["rk4"][1]["env_steps"] / best["rk4"]
            for name, (backend, info) in built.items():
                sps = info["env_steps"] / best[name]
                rows.append(
                    dict(
                        case=name,
                        envs=envs,
                        steps=steps,
                        where=backend.where,
                        jax=info["jax"],
                        compile_s=info["compile_s"],
                        setup_s=info.get("setup_s"),
                        run_s=best[name],
                        env_steps=info["env_steps"],
                        steps_per_s=sps,
                        time_vs_rk4=rk4_sps / sps,
                        ours_vs_crazyflow=(sps / cf_best) if cf_best and not name.startswith("cf_") else None,
                    )
                )
    finally:
        if worker:
            worker.close()

    _peers.print_machine(record)
    print(
        f"{'envs':>6} {'case':<15} {'compile s':>9} {'run s':>8} {'env-steps/s':>12} {'x rk4 time':>10} "
        f"{'ours/cf':>8}"
    )
    for r in rows:
        ratio = f"{r['ours_vs_crazyflow']:.1f}" if r["ours_vs_crazyflow"] else "-"
        print(
            f"{r['envs']:>6} {r['case']:<15} {r['compile_s']:>9.2f} {r['run_s']:>8.4f} "
            f"{r['steps_per_s']:>12.3e} {r['time_vs_rk4']:>10.2f} {ratio:>8}"
        )
    print("ours/cf: our env-steps/s over the faster of cf_rate_stepn and cf_rate_scan at the same env count")
    goals = {}
    for r in rows:
        if r["case"] == "env_nominal" and r["envs"] == 1024:
            goals["env_vs_rk4_time_le_1.5"] = dict(value=r["time_vs_rk4"], met=r["time_vs_rk4"] <= 1.5)
            if r["ours_vs_crazyflow"]:
                goals["env_vs_crazyflow_ge_50x"] = dict(
                    value=r["ours_vs_crazyflow"], met=r["ours_vs_crazyflow"] >= 50
                )
    _peers.print_goals(goals, "{:.2f}")
    record.update(
        versions=_peers.versions(["jax", "jaxlib", "ttd3_jax"]),
        crazyflow_worker=cf_versions or None,
        quick=args.quick,
        repeats=args.repeats,
        rows=rows,
        goals=goals,
    )
    _peers.append_record(args.out, record)
    return record


if __name__ == "__main__":
    main()
