"""Nonlinear MPC baseline in pure JAX (spec §2.6): Gauss-Newton SQP, single shooting, RTI.

Model: the env's own :func:`~ttd3_jax.sim.dynamics.rk4_step` and ``QuadParams`` (rate model
included), the input held over each node interval (``node_substeps`` RK4 steps of
``dt_node`` s).  A ``firmware`` vehicle (``QuadParams.loop`` set: a 1 kHz rate PID through rotor
lags, which a 50 ms node step cannot integrate) is modelled by :mod:`ttd3_jax.control.loop_model`
instead: the PID, rotors and rigid body as a continuous-time system with the body torque, the
PID's integral and the collective thrust as extra states (``loop_substeps`` RK4 steps per node);
the controller carries those unsensed states from step to step through the same model under the
commands it applied (:func:`~ttd3_jax.control.loop_model.propagate_hidden`).  The plan ``U``
(N, 4) is physical ``[thrust, ω_x, ω_y, ω_z]`` inside the env's box.  Wind is not modelled.

Cost (rpg_mpc default weights, ``Q`` times ``weight_scale``, 4 from the validation-track
tuning of ``experiments/tune_nmpc.py``)::

    J(U) = ½ Σ_{i=1..N} [ (p_i − p_ref,i)ᵀ Q_p (p_i − p_ref,i) + (v_i − v_ref,i)ᵀ Q_v (v_i − v_ref,i)
                          + vec(q_ref,i⁻¹ ⊗ q_i)ᵀ Q_q vec(q_ref,i⁻¹ ⊗ q_i) ]
         + ½ Σ_{i=0..N−1} (ũ_i − ũ_ref,i)ᵀ R (ũ_i − ũ_ref,i)

References are the track's analytic p/v/a at the node times (full preview).  ``q_ref`` is
the tilt-only rotation from world z to a_ref + g (differential flatness, zero heading, as
rpg's ``acc_and_heading_to_orientation``); the input reference is ``(‖a_ref + g‖, 0, 0, 0)``;
the quaternion error takes the sign with a non-negative scalar part.  The input residual is
on ``ũ = (c, ω)`` with the mass-normalised thrust c (m/s²), as in rpg_mpc, so ``R =
diag(w_input)`` means the same under both thrust units.

Solver: r(U) stacks the weighted state residuals (9 per node); its Jacobian J (9N × 4N)
comes from the node Jacobians of the RK4 step (all nodes at once) and a condensing
recursion (:meth:`NMPC.linearize`), so ``H = JᵀJ + R + reg·I`` and ``g = Jᵀr + R(U −
U_ref)``.  The box QP on ΔU is solved by projected Newton (:meth:`NMPC._box_qp`: one
Cholesky per active-set change, at most ``qp_iters``; with no active bound, the common
case, it is the exact Newton step).  The step is ``U + αΔU`` with the first α in
(1, ½, ¼, ⅛) that lowers the true cost (α < 1 only tried when α = 1 fails), else U is kept
(``line_search=False``: α = 1).

Closed loop (:func:`nmpc_controller`): the first call runs ``sqp_iters_first`` iterations
from ``U_ref``; later ones re-solve every ``solve_every`` control steps with ``sqp_iters``
(1 = real-time iteration) from the previous plan shifted by the elapsed time, which is
applied as planned in between.  Everything is jit/vmap-able; there is no Python per step.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from flax import struct
from jax.flatten_util import ravel_pytree
from jax.scipy.linalg import cho_solve

from ttd3_jax import checks
from ttd3_jax.control import loop_model as lm
from ttd3_jax.control.closed_loop import Controller
from ttd3_jax.sim import trajectories as tr
from ttd3_jax.sim.dynamics import QuadParams, QuadState, quat_conj, quat_mul, rk4_step
from ttd3_jax.sim.env import control_to_action

LINE_SEARCH_ALPHAS = (1.0, 0.5, 0.25, 0.125)
QP_STEPS = tuple(0.5**i for i in range(10))  # step sizes the box QP's projected Newton tries
QP_EPS = 0.1  # most distance (scaled units) at which a bound counts as active


@dataclasses.dataclass(frozen=True)
class NMPCConfig:
    """NMPC settings (spec §2.6). Units: seconds; weights on m, m/s, rad-ish quaternion
    vector part, and (m/s², rad/s) inputs (see the module docstring)."""

    horizon: int = 20  # N, number of nodes (inputs)
    dt_node: float = 0.05  # s, node spacing (N·dt_node = 1 s horizon)
    w_pos: tuple[float, float, float] = (200.0, 200.0, 500.0)  # diag Q_p, 1/m²
    w_vel: tuple[float, float, float] = (10.0, 10.0, 10.0)  # diag Q_v
    w_att: tuple[float, float, float] = (50.0, 50.0, 5.0)  # diag Q_q on vec(q_ref⁻¹⊗q)
    w_input: tuple[float, float, float, float] = (0.1, 0.1, 0.1, 0.1)  # diag R on (c, ω)
    # Multiplies Q_p, Q_v, Q_q (the state-vs-input trade-off).  4 is the choice of the spec's
    # {¼, 1, 4} × N ∈ {10, 20, 40} grid on the validation tracks (experiments/tune_nmpc.py).
    weight_scale: float = 4.0
    sqp_iters_first: int = 30  # Gauss-Newton iterations of the first solve
    sqp_iters: int = 1  # iterations of every later solve (1 = RTI)
    qp_iters: int = 8  # most projected-Newton iterations of the box QP (it stops when solved)
    solve_every: int = 1  # control steps between re-solves
    line_search: bool = True  # α ∈ {1, ½, ¼, ⅛} on the true cost
    node_substeps: int = 1  # RK4 steps per node interval
    # RK4 steps per node interval of a firmware vehicle's loop model (control.loop_model): 10 ms
    # steps, 4-5 per period of its rate loop's oscillation (27 rad/s)
    loop_substeps: int = 5
    regularization: float = 1e-6  # added to the diagonal of H

    def __post_init__(self):
        for name, hi in _INTEGERS.items():
            checks.integer(f"NMPCConfig.{name}", getattr(self, name), 1, hi)
        for name, hi in _NUMBERS.items():
            checks.number(f"NMPCConfig.{name}", getattr(self, name), 0, hi, lo_open=True)
        for name, positive in _WEIGHTS.items():
            v, n, sign = getattr(self, name), 4 if name == "w_input" else 3, "> 0" if positive else ">= 0"
            ok = (
                isinstance(v, tuple | list) and len(v) == n and all(checks.is_number(x) and x >= 0 for x in v)
            )
            if not ok or (positive and min(v) <= 0):
                checks.fail(f"NMPCConfig.{name}", f"{n} finite numbers {sign}", v)
        if not isinstance(self.line_search, bool):
            raise ValueError(f"NMPCConfig.line_search must be True or False, got {self.line_search!r}")


# the bounds NMPCConfig checks: integers in [1, hi], numbers in (0, hi], weights (> 0 if True)
_INTEGERS = {"horizon": 500, "sqp_iters_first": 1000, "sqp_iters": 1000, "qp_iters": 1000,
             "solve_every": 100_000, "node_substeps": 100, "loop_substeps": 100}  # fmt: skip
_NUMBERS = {"dt_node": 1.0, "weight_scale": 1e6, "regularization": 1.0}
_WEIGHTS = {"w_pos": True, "w_vel": False, "w_att": False, "w_input": False}


class References(NamedTuple):
    """Per-node references: states at nodes 1..N, inputs at nodes 0..N-1."""

    pos: jax.Array  # (N, 3) m
    vel: jax.Array  # (N, 3) m/s
    quat: jax.Array  # (N, 4) flatness attitude, scalar first
    u: jax.Array  # (N, 4) physical input reference [thrust, 0, 0, 0]


@struct.dataclass
class NMPCCarry:
    """Controller memory between control steps."""

    plan: jax.Array  # (N, 4) physical inputs from the last solve
    age: jax.Array  # int32, control steps since the plan was computed
    solves: jax.Array  # int32, number of solves so far
    cost: jax.Array  # cost J of the plan at its solve (diagnostic)
    # a firmware vehicle's unsensed loop states (loop_model.HIDDEN,) at this step; (0,) otherwise
    hidden: jax.Array


def models_loop(quad: QuadParams) -> bool:
    """Whether the NMPC models ``quad``'s inner loop (:mod:`~ttd3_jax.control.loop_model`): a
    ``firmware`` vehicle; every other vehicle is modelled by the env's own dynamics."""
    return quad.rate_model == "firmware"


def rigid_body(x: QuadState) -> QuadState:
    """``x``'s position, velocity, attitude and body rates (what the controller senses: a
    ``firmware`` state without its rotors and PID)."""
    return QuadState(p=x.p, v=x.v, q=x.q, w=x.w)


def tilt_quaternion(z: jax.Array) -> jax.Array:
    """Minimal rotation (scalar first, q_z = 0) taking world z onto the unit vector ``z`` (..., 3)."""
    q = jnp.stack([1.0 + z[..., 2], -z[..., 1], z[..., 0], jnp.zeros_like(z[..., 0])], -1)
    return q / jnp.linalg.norm(q, axis=-1, keepdims=True)


class NMPC:
    """The optimal-control problem and its solver for one environment configuration.

    Every method is a pure function of arrays (jit/vmap them freely).
    """

    def __init__(self, env_config, cfg: NMPCConfig | None = None):
        self.env_config = env_config
        self.cfg = cfg = cfg or NMPCConfig()
        self.params: QuadParams = env_config.vehicle.quad
        self.loop = models_loop(self.params)
        self.dt = env_config.dt
        # physics step offsets of the nodes 0..N (reference sampling)
        self.node_steps = tuple(int(round(i * cfg.dt_node / self.dt)) for i in range(cfg.horizon + 1))
        p = self.params
        self._newton = p.thrust_units == "newton"
        self._lb = (p.thrust_min, p.rate_min, p.rate_min, p.rate_min)
        self._ub = (p.thrust_max, p.rate_max, p.rate_max, p.rate_max)
        s = cfg.weight_scale
        self._sqrt_q = tuple(math.sqrt(s * w) for w in (*cfg.w_pos, *cfg.w_vel, *cfg.w_att))
        # R on the physical input: thrust weight rescaled so that it acts on c = f/m
        m2 = p.mass**2 if self._newton else 1.0
        self._r = (cfg.w_input[0] / m2, *cfg.w_input[1:])

    def bounds(self, dtype) -> tuple[jax.Array, jax.Array]:
        n = self.cfg.horizon
        lb = jnp.broadcast_to(jnp.asarray(self._lb, dtype), (n, 4))
        ub = jnp.broadcast_to(jnp.asarray(self._ub, dtype), (n, 4))
        return lb, ub

    def references(self, track: tr.Track, k: jax.Array) -> References:
        """References for a solve at physics step ``k`` (int)."""
        ks = k + jnp.asarray(self.node_steps, jnp.int32)
        pos, vel, acc = tr.evaluate(track, ks, self.dt)  # (N+1, 3)
        f = pos.dtype
        thrust_acc = acc + jnp.asarray([0.0, 0.0, self.params.gravity], f)
        c = jnp.linalg.norm(thrust_acc, axis=-1)
        quat = tilt_quaternion(thrust_acc / c[:, None])
        thrust = c * self.params.mass if self._newton else c
        u = jnp.concatenate([thrust[:, None], jnp.zeros((thrust.shape[0], 3), f)], -1)
        lb, ub = self.bounds(f)
        u = jnp.clip(u[:-1], lb, ub)
        return References(pos=pos[1:], vel=vel[1:], quat=quat[1:], u=u)

    def node_step(self, x: QuadState, u: jax.Array) -> QuadState:
        """The model's state one node interval after ``x`` under the input ``u`` (4,)."""
        cfg = self.cfg
        if self.loop:
            return lm.step(self.params, x, u, cfg.dt_node, cfg.loop_substeps)
        return rk4_step(self.params, x, u, cfg.dt_node, substeps=cfg.node_substeps)

    def model_state(self, sensed: QuadState, hidden: jax.Array) -> QuadState:
        """The model's state from the sensed rigid body and the carried hidden states."""
        return lm.with_hidden(sensed, hidden) if self.loop else sensed

    def initial_hidden(self, dtype) -> jax.Array:
        """The hidden states at the start of an episode (the vehicle at rest)."""
        return lm.hover_hidden(self.params, dtype) if self.loop else jnp.zeros((0,), dtype)

    def next_hidden(self, sensed: QuadState, hidden: jax.Array, u: jax.Array, seconds: float) -> jax.Array:
        """The hidden states ``seconds`` after ``sensed`` under the applied input ``u``."""
        if not self.loop:
            return hidden
        substeps = max(1, math.ceil(seconds / (self.cfg.dt_node / self.cfg.loop_substeps) - 1e-9))
        return lm.propagate_hidden(self.params, sensed, hidden, u, seconds, substeps)

    def rollout(self, x0: QuadState, U: jax.Array) -> QuadState:
        """States at nodes 1..N (each leaf with a leading axis N) under the ZOH plan ``U``."""

        def step(x, u):
            x = self.node_step(x, u)
            return x, x

        return jax.lax.scan(step, x0, U)[1]

    def state_residual(self, x0: QuadState, ref: References, U: jax.Array) -> jax.Array:
        """Weighted state residual (9N,): √Q_p e_p, √Q_v e_v, √Q_q vec(q_ref⁻¹⊗q) per node."""
        xs = self.rollout(x0, U)
        dq = quat_mul(quat_conj(ref.quat), xs.q)
        dq_vec = jnp.where(dq[:, :1] < 0, -dq[:, 1:], dq[:, 1:])
        e = jnp.concatenate([xs.p - ref.pos, xs.v - ref.vel, dq_vec], -1)  # (N, 9)
        return (e * jnp.asarray(self._sqrt_q, e.dtype)).reshape(-1)

    def cost(self, x0: QuadState, ref: References, U: jax.Array) -> jax.Array:
        """True cost J(U) (see the module docstring)."""
        r = self.state_residual(x0, ref, U)
        du = U - ref.u
        return 0.5 * (jnp.sum(r * r) + jnp.sum(jnp.asarray(self._r, U.dtype) * du * du))

    def _box_qp(self, H, g, lo, hi):
        """min ½ΔᵀHΔ + gᵀΔ, lo ≤ Δ ≤ hi (lo ≤ 0 ≤ hi); returns Δ.

        Projected Newton (Bertsekas 1982) on Jacobi-scaled variables ``Δ = D z``, ``D =
        diag(H)^{-½}``, from z = 0: each iteration fixes the ε-active bounds whose gradient
        points out of the box, solves the Newton system on the rest (one Cholesky) and takes
        the first step of ``QP_STEPS`` along the projection arc that passes Armijo's test.
        It stops when the active set repeats after a full, unclipped step (the solution: in
        most RTI steps no bound is active and this is the first iteration), when no step
        decreases the objective, or after ``qp_iters`` iterations."""
        d = jax.lax.rsqrt(jnp.diag(H))
        Hs = H * d[:, None] * d[None, :]
        gs, ls, hs = g * d, lo / d, hi / d
        dt = g.dtype
        steps = jnp.asarray(QP_STEPS, dt)

        def clamped(z, grad):
            eps = jnp.minimum(QP_EPS, jnp.linalg.norm(z - jnp.clip(z - grad, ls, hs)))
            return ((z <= ls + eps) & (grad > 0)) | ((z >= hs - eps) & (grad < 0))

        def body(c):
            z, grad, fixed, it, _ = c
            free = (~fixed).astype(dt)
            Hf = Hs * free[:, None] * free[None, :] + jnp.diag(1.0 - free)
            step = -cho_solve((jnp.linalg.cholesky(Hf), True), grad * free)
            Z = jnp.clip(z[:, None] + step[:, None] * steps[None], ls[:, None], hs[:, None])
            dZ = Z - z[:, None]
            # objective change of each candidate, and Armijo's test along the arc
            df = jnp.sum(dZ * (0.5 * (Hs @ dZ) + grad[:, None]), 0)
            ok = df <= 1e-4 * steps * jnp.dot(grad, step)
            i = jnp.argmax(ok)
            z_new = jnp.where(ok[i], Z[:, i], z)
            grad_new = Hs @ z_new + gs
            fixed_new = clamped(z_new, grad_new)
            full = ok[0] & jnp.all(dZ[:, 0] == step)
            done = ~ok[i] | (full & jnp.all(fixed_new == fixed))
            return z_new, grad_new, fixed_new, it + 1, done

        z0 = jnp.zeros_like(g)  # feasible: U itself is inside the box
        c0 = (z0, gs, clamped(z0, gs), 0, False)
        z = jax.lax.while_loop(lambda c: (c[3] < self.cfg.qp_iters) & ~c[4], body, c0)[0]
        return z * d

    def linearize(self, x0: QuadState, ref: References, U: jax.Array) -> tuple[jax.Array, jax.Array]:
        """:meth:`state_residual` r (9N,) and its Jacobian (9N, 4N) in ``U`` (flattened).

        One rollout, then the node Jacobians ``A_i = ∂x_{i+1}/∂x_i``, ``B_i = ∂x_{i+1}/∂u_i``
        and the attitude residual's ``∂r_i/∂q_i``, all nodes at once (``vmap`` of ``jacfwd``),
        and the sensitivities ``S_{i+1} = A_i S_i + [0 … B_i … 0]`` (``S_i = ∂x_i/∂U``) in one
        short scan: the same J as ``jacfwd`` through the rollout, without carrying 4N tangents
        through the N sequential RK4 steps (faster on CPU: benchmarks/nmpc_speed.py)."""
        n = self.cfg.horizon
        xf0, unravel = ravel_pytree(x0)
        nx = xf0.shape[0]
        sqrt_q = jnp.asarray(self._sqrt_q, U.dtype)

        def f(xf, u):
            return ravel_pytree(self.node_step(unravel(xf), u))[0]

        def att_residual(q, q_ref):
            dq = quat_mul(quat_conj(q_ref), q)
            return jnp.where(dq[:1] < 0, -dq[1:], dq[1:]) * sqrt_q[6:]

        xs = jax.lax.scan(lambda x, u: (f(x, u),) * 2, xf0, U)[1]  # (N, nx), nodes 1..N
        A, B = jax.vmap(jax.jacfwd(f, argnums=(0, 1)))(jnp.concatenate([xf0[None], xs[:-1]]), U)
        # ravel_pytree(QuadState) is [p, v, q, w, …]: ∂r/∂(p, v) is diagonal, ∂r/∂q is Cq
        q_ref = ref.quat
        r = jnp.concatenate([(xs[:, :3] - ref.pos) * sqrt_q[:3], (xs[:, 3:6] - ref.vel) * sqrt_q[3:6],
                             jax.vmap(att_residual)(xs[:, 6:10], q_ref)], -1)  # fmt: skip
        Cq = jax.vmap(jax.jacfwd(att_residual))(xs[:, 6:10], q_ref)  # (N, 3, 4)

        def sensitivity(S, abe):  # S (nx, N, 4): ∂x_i/∂U
            a, b, e = abe
            S = (a @ S.reshape(nx, 4 * n)).reshape(nx, n, 4) + b[:, None, :] * e[None, :, None]
            return S, S

        S0 = jnp.zeros((nx, n, 4), U.dtype)
        S = jax.lax.scan(sensitivity, S0, (A, B, jnp.eye(n, dtype=U.dtype)))[1].reshape(n, nx, 4 * n)
        J = jnp.concatenate(
            [S[:, :6] * sqrt_q[None, :6, None], jnp.einsum("jrq,jqk->jrk", Cq, S[:, 6:10])], 1
        )
        return r.reshape(-1), J.reshape(9 * n, 4 * n)

    def gn_step(self, x0: QuadState, ref: References, U: jax.Array, cost_u: jax.Array | None = None):
        """One Gauss-Newton SQP iteration. Returns ``(U_new, J(U_new))``."""
        cfg = self.cfg
        u_flat = U.reshape(-1)
        r, J = self.linearize(x0, ref, U)
        rw = jnp.tile(jnp.asarray(self._r, U.dtype), cfg.horizon)
        du = u_flat - ref.u.reshape(-1)
        if cost_u is None:
            cost_u = 0.5 * (jnp.sum(r * r) + jnp.sum(rw * du * du))
        H = J.T @ J + jnp.diag(rw + cfg.regularization)
        g = r @ J + rw * du
        lb, ub = self.bounds(U.dtype)
        delta = self._box_qp(H, g, lb.reshape(-1) - u_flat, ub.reshape(-1) - u_flat).reshape(U.shape)
        if not cfg.line_search:
            U_new = jnp.clip(U + delta, lb, ub)
            return U_new, self.cost(x0, ref, U_new)
        U_full = jnp.clip(U + delta, lb, ub)
        cost_full = self.cost(x0, ref, U_full)

        def backtrack(_):  # the full step failed (rare after an exact QP solve): try α < 1
            alphas = jnp.asarray(LINE_SEARCH_ALPHAS[1:], U.dtype)
            cands = jnp.clip(U[None] + alphas[:, None, None] * delta[None], lb, ub)
            costs = jax.vmap(lambda u: self.cost(x0, ref, u))(cands)
            ok = jnp.isfinite(costs) & (costs < cost_u)
            i = jnp.argmax(ok)  # first α that decreases the cost
            return jnp.where(ok[i], cands[i], U), jnp.where(ok[i], costs[i], cost_u)

        full_ok = jnp.isfinite(cost_full) & (cost_full < cost_u)
        return jax.lax.cond(full_ok, lambda _: (U_full, cost_full), backtrack, None)

    def solve(self, x0: QuadState, ref: References, U: jax.Array, iters) -> tuple[jax.Array, jax.Array]:
        """``iters`` (may be traced) Gauss-Newton iterations from ``U``; returns (U, J(U))."""
        lb, ub = self.bounds(U.dtype)
        U = jnp.clip(U, lb, ub)
        c0 = jnp.full((), jnp.nan, U.dtype)  # J of the first iterate comes from its linearisation
        return jax.lax.fori_loop(0, iters, lambda _, c: self.gn_step(x0, ref, c[0]), (U, c0))

    def shift(self, U: jax.Array, seconds) -> jax.Array:
        """Warm start: the plan advanced by ``seconds`` (linear interpolation between
        nodes, last node held)."""
        n = self.cfg.horizon
        s = jnp.asarray(seconds, U.dtype) / self.cfg.dt_node + jnp.arange(n, dtype=U.dtype)
        s = jnp.clip(s, 0.0, n - 1.0)
        i0 = jnp.floor(s).astype(jnp.int32)
        i1 = jnp.minimum(i0 + 1, n - 1)
        f = (s - i0.astype(U.dtype))[:, None]
        return (1.0 - f) * U[i0] + f * U[i1]

    def plan_input(self, U: jax.Array, seconds) -> jax.Array:
        """Input of the ZOH plan ``U`` at ``seconds`` after its start."""
        i = jnp.floor(jnp.asarray(seconds, U.dtype) / self.cfg.dt_node + 1e-6).astype(jnp.int32)
        return U[jnp.clip(i, 0, self.cfg.horizon - 1)]


def nmpc_controller(env_config, cfg: NMPCConfig | None = None):
    """NMPC as a :class:`~ttd3_jax.control.closed_loop.Controller` for ``env_config`` (its
    model, bounds, action map, ``dt`` and ``action_repeat``)."""
    mpc = NMPC(env_config, cfg)
    cfg = mpc.cfg
    control_dt = env_config.control_dt

    def init(state) -> NMPCCarry:
        ps = state.pipeline_state
        ref = mpc.references(ps.track, ps.k)
        zero = jnp.zeros((), jnp.int32)
        hidden = mpc.initial_hidden(ref.u.dtype)
        return NMPCCarry(plan=ref.u, age=zero, solves=zero, cost=jnp.zeros((), ref.u.dtype), hidden=hidden)

    def act(carry: NMPCCarry, state):
        ps = state.pipeline_state
        sensed = rigid_body(ps.quad)

        def resolve(c: NMPCCarry) -> NMPCCarry:
            ref = mpc.references(ps.track, ps.k)
            warm = mpc.shift(c.plan, c.age.astype(c.plan.dtype) * control_dt)
            iters = jnp.where(c.solves == 0, cfg.sqp_iters_first, cfg.sqp_iters)
            U, J = mpc.solve(mpc.model_state(sensed, c.hidden), ref, warm, iters)
            return c.replace(plan=U, age=jnp.zeros_like(c.age), solves=c.solves + 1, cost=J)

        due = (carry.solves == 0) | (carry.age >= cfg.solve_every)
        carry = jax.lax.cond(due, resolve, lambda c: c, carry)
        u = mpc.plan_input(carry.plan, carry.age.astype(carry.plan.dtype) * control_dt)
        a = control_to_action(env_config, u).astype(state.obs.dtype)
        hidden = mpc.next_hidden(sensed, carry.hidden, u, control_dt)
        return a, carry.replace(age=carry.age + 1, hidden=hidden)

    return Controller(init=init, act=act)
