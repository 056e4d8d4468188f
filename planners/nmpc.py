"""NMPC peer planner: the paper's eq. 21 solved by CasADi + IPOPT, with the same MLP dynamics and tuning.

Section IV of the paper shows that BIMP approximately solves an NMPC problem; this module solves that problem
directly with a gradient-based solver, so the EnKTS planner can be compared against it:

    min_{U, X}  sum_{t=1..H} rho_3(|r(x_t)|^2_{Sigma_ref^-1}) + sum_{t=0..H-1} [rho_2(|s(x_{t+1}, u_t)|^2_{Sigma_in^-1})
                                                                            + rho_2(|u_t - u_{t-1}|^2_{Sigma_w^-1})]
    s.t.  x_{t+1} = f(x_t, u_t)                    (the shipped MLP, written as CasADi expressions)
          a_min <= a_t <= a_max, |delta_t| <= delta_max, |u_t - u_{t-1}| <= rate    (eq. 4-5, hard)
          every body corner inside the road edges, margin BarrierShape.edge_margin    (eq. 3, hard)
          (ds / semi_s)^p + (dl / semi_l)^p >= 1 per OV and step, p even               (eq. 2, hard, smooth)

- ``nmpc`` (``nu = inf``): rho_n(q) = q / 2, the quadratic tracking cost of eq. 21 as a negative log-likelihood;
  weights are the inverse squared noise scales ``sigma_ref``, ``sigma_input``, ``sigma_du`` of the shared planner
  problem (``configs/problem.yaml``, the steering's scaled to the road's bound by ``problem.for_road``), so all
  planners trade tracking against smoothness the same way.
- ``nmpc-t`` (``nu`` = the problem's ``nu``): rho_n(q) = (nu + n) / 2 log(1 + q / nu), the Student's-t log cost
  of section IV (it tends to q / 2 as nu -> inf).

The residuals are those of :func:`bimp.planners.problem.measure` (road frame: lateral offset to the reference lane,
heading relative to the road, speed error; acceleration minus the reference's rate, steering minus the
curvature feed-forward), each input ``u_t`` paired with the state ``x_{t+1}`` it reaches and the references of
time ``t + 1``, as every planner measures ``x_1 .. x_H``. ``u_{-1}`` is the input applied last (from the
observation); ``x_0`` is the current state, so its own residual is a constant and left out. The OV keep-out is a
smooth superellipse through the semi-axes of the virtual system's keep-out box (time headway and braking room, see
:func:`keep_out_semi_axes`).
An ellipse (p = 2) cuts the box's corners by 29% of each semi-axis, and in the emergency brake NMPC used that
to stop between the lanes 0.3 m from an OV; p = 4 (16%) stays closer to the box the other planners see and
stopped 1.7 m behind. OV motion comes from :func:`bimp.planners.problem.predict_obstacles`. The road's Frenet frame
is written as CasADi expressions of ``(x, y)`` mirroring :meth:`bimp.envs.road.RoadGeometry.to_frenet` (tests check
they agree), with the road's shape as NLP parameters, so one compiled solver serves every redrawn road.

Solver: IPOPT (MUMPS), multiple shooting (X and U are both decision variables: the MLP's nonlinearity stays
local to each step), exact Hessian by CasADi's AD, warm start from the previous solution shifted by one
step. Caps: ``max_iter`` is the working one (warm solves take 10-15 iterations), so the actions do not depend
on the machine's load; ``max_cpu_time`` only guards against a pathological solve. The first solve of an episode
has no warm start and its own, larger caps (``cold_max_iter``, ``cold_max_cpu_time``), as a controller solves
once before it engages: with the closed-loop caps it can stop short at every step while the state drifts into
the keep-out (seen on overtaking seed 0: 20-38 iterations needed, never reached, collision on a held input).
A solve that ends in IPOPT success is used; one stopped by a cap is used if its iterate is feasible
(``feasibility_tol``), counted in ``capped``; anything else (infeasible, restoration failure, non-finite
numbers, an exception) falls back to the last usable plan's next control (or holds the last input if there is
none), counted in ``failures``, and the next solve starts from the unusable iterate if it is finite (it is
further on than the old guess). Never a crash, never a non-finite action. No random draws: ``reset(seed)``
only forgets the warm start, and while the iteration caps bind before the CPU-time caps the same observations
give the same actions.
"""

from __future__ import annotations

import math
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Callable

import casadi as ca
import numpy as np

from bimp.configs import ConfigError, check_fields
from bimp.envs.scene import Scene, leads
from bimp.planners.dynamics import BicycleModel, dynamics_files, model_from_name, steer_bound
from bimp.planners.nmpc_casadi import (  # re-exported: the program's pieces, as bimp.planners.nmpc named them
    ROAD_PARAMS,
    bicycle_function,
    closed_form,
    curvature_at,
    frenet,
    heading_at,
    keep_out_semi_axes,
    mlp_function,
    road_params,
    robust_cost,
)
from bimp.planners.problem import (
    BarrierShape,
    ProblemConfig,
    for_road,
    load_planner_config,
    make_problem,
    predict_obstacles,
    reference_profile,
    road_changes,
)
from bimp.planners.problem import search_space as problem_search_space

_SUCCESS = ("Solve_Succeeded", "Solved_To_Acceptable_Level")
_CAPPED = ("Maximum_Iterations_Exceeded", "Maximum_CpuTime_Exceeded", "Maximum_WallTime_Exceeded")
_ABSENT = 1e3  # added to an absent OV's keep-out value: the constraint can never bind


# NMPC's bounds are hard constraints: the margin only keeps IPOPT's tolerance and the float32 action inside the
# env's bounds (the soft barriers of EnKTS and MPPI need the shared problem's 0.05).
HARD_BOUND_MARGIN = 1e-3
HARD_BOUNDS = {"problem": {"barrier": {"bound_margin": HARD_BOUND_MARGIN}}}  # the layer over the shared problem


@dataclass(frozen=True)
class NMPCConfig:
    """NMPC's solver settings and its planning problem.

    problem: the virtual system (:class:`bimp.planners.problem.ProblemConfig`), as every planner holds it: its
    horizon is NMPC's, its noise scales the cost's weights (inverse squares), its barrier margins the constraints'.
    ``problem.nu`` is the degrees of freedom of the Student's-t log cost (``inf``: the quadratic cost of eq. 21,
    ``nmpc``'s default; ``nmpc-t`` takes the shared problem's): the same Student's-t as the virtual system's
    noise, one range of nu whichever planner solves it. ``problem.barrier.bound_margin`` is the relative margin by
    which NMPC tightens the input and rate bounds, as the barriers of the other planners do; NMPC's bounds are hard
    constraints, so it only has to keep IPOPT's tolerance and the float32 action inside the env's bounds: NMPC's
    default is :data:`HARD_BOUND_MARGIN` = 1e-3 (this field was ``bound_tightening``), not the shared problem's 0.05.

    max_iter: IPOPT iteration cap per warm-started solve (>= 0); max_cpu_time [s]: IPOPT CPU-time cap per
    warm-started solve; cold_max_iter, cold_max_cpu_time: the same for the first solve of an episode; tol: IPOPT's
    convergence tolerance; hessian: ``"exact"`` (CasADi AD) or ``"limited-memory"`` (L-BFGS); feasibility_tol:
    largest constraint violation of a capped iterate that is still used; keep_out_power: even exponent p >= 2 of
    the keep-out superellipse (2: an ellipse); slack_penalty: weight > 0 of the exact (L1) penalty on slack
    variables that soften the keep-out and road-edge constraints (``inf``: hard constraints, the paper's eq. 21;
    with them a sudden brake ahead makes the problem infeasible, IPOPT fails at every step and the fallback drives
    into the OV). A bad value raises :class:`bimp.configs.ConfigError` naming the key and the value (types by
    :func:`bimp.configs.check_fields`).
    """

    max_iter: int = 30
    max_cpu_time: float = 1.0
    cold_max_iter: int = 200
    cold_max_cpu_time: float = 5.0
    tol: float = 1e-6
    hessian: str = "exact"
    feasibility_tol: float = 1e-4
    keep_out_power: int = 4
    slack_penalty: float = 1e4
    problem: ProblemConfig = field(default_factory=lambda: ProblemConfig(
        nu=math.inf, barrier=BarrierShape(bound_margin=HARD_BOUND_MARGIN)))

    # Old keys, refused naming their new place (bimp.planners.problem.load_planner_config).
    MOVED = {"bound_tightening": "problem.barrier.bound_margin"}

    def __post_init__(self) -> None:
        check_fields(self, allow_inf=("slack_penalty",))  # a problem mapping -> ProblemConfig, checked
        for key in ("max_iter", "cold_max_iter"):
            if getattr(self, key) < 0:
                raise ConfigError(key, "an int >= 0", getattr(self, key))
        for key in ("max_cpu_time", "cold_max_cpu_time", "tol", "feasibility_tol"):
            if not getattr(self, key) > 0:
                raise ConfigError(key, "a finite number > 0", getattr(self, key))
        if self.hessian not in ("exact", "limited-memory"):
            raise ConfigError("hessian", "'exact' or 'limited-memory'", self.hessian)
        if self.keep_out_power < 2 or self.keep_out_power % 2:
            raise ConfigError("keep_out_power", "an even int >= 2", self.keep_out_power)
        if not self.slack_penalty > 0:
            raise ConfigError("slack_penalty", "> 0 (inf for hard constraints)", self.slack_penalty)


# --- the planner ---------------------------------------------------------------------------------------------
@dataclass
class _Problem:
    """A compiled NLP for one scene layout: its warm and cold solvers (caps differ), variable and constraint
    bounds."""

    solver: ca.Function
    cold_solver: ca.Function
    lbx: np.ndarray
    ubx: np.ndarray
    lbg: np.ndarray
    ubg: np.ndarray
    n_slack: int = 0  # slack variables after X and U in the decision vector (soft constraints)


class NMPCPlanner:
    """NMPC (eq. 21) as an :class:`bimp.agents.Policy`.

    scene: a :class:`bimp.envs.Scene` or a callable returning the current one (``lambda: env.unwrapped.scene``);
    config: solver settings and the problem (cost weights = inverse squared noise scales, barrier margins,
    horizon); dynamics: a CasADi ``Function f(x (4,), u (2,)) -> (4,)`` (default: the model
    ``config.problem.dynamics`` names, as EnKTS: :func:`mlp_function` of the shipped MLP or of a weights file, or
    :func:`bicycle_function`).

    Attributes after ``act``: ``failures`` (fallback actions), ``capped`` (cap-stopped but feasible solves used),
    ``statuses`` (IPOPT return statuses), ``solve_times`` [s] and ``iterations`` per solve, ``plan`` (the last
    usable solution ``(X (H + 1, 4), U (H, 2))``), ``step_info`` (this step's ``status``, ``fallback``,
    ``iterations`` and the largest ``slack`` of the solve: the episode loop records it per step).
    """

    def __init__(self, scene: Scene | Callable[[], Scene], config: NMPCConfig = NMPCConfig(),
                 dynamics: ca.Function | None = None):
        self.config = config
        self.horizon = config.problem.horizon
        self._scene = scene if callable(scene) else (lambda: scene)
        built = self._scene()  # the scene at build: what the road asks of the planner
        closed_form(built)  # refused at build, where bimp evaluate names it, not in every episode
        self._model_dt = None  # the step the learned model was trained for, checked against the scene's
        # The weights by content (in the config's hash) and by name; a model handed in directly is the caller's.
        bound = steer_bound(built)
        self.files, self.artifacts = dynamics_files(config.problem.dynamics, bound) if dynamics is None else ({}, {})
        # what the road changes in the problem, for the record
        self.road = road_changes(config.problem, bound, leads(built))
        if dynamics is None:
            model = model_from_name(config.problem.dynamics, bound)
            build = bicycle_function if isinstance(model, BicycleModel) else mlp_function
            dynamics, self._model_dt = build(model), model.dt
        self.f = dynamics
        self._problems: dict[tuple, _Problem] = {}
        self.failures = self.capped = 0
        self.statuses: Counter[str] = Counter()
        self.solve_times: list[float] = []
        self.iterations: list[int] = []
        self.reset()

    def reset(self, seed: int | None = None) -> None:
        """Start a new episode: forget the warm start. (``seed`` is accepted for the protocol; nothing is random.)"""
        self._guess: tuple[np.ndarray, np.ndarray] | None = None  # last iterate: X (H, 4) = x_1..x_H, U (H, 2)
        self._controls: np.ndarray | None = None  # the last usable plan's controls (H, 2), shifted at every step
        self.plan: tuple[np.ndarray, np.ndarray] | None = None
        self.step_info: dict = {}  # this step's solve, set by act

    # --- Policy ------------------------------------------------------------------------------------------
    def act(self, obs: np.ndarray) -> np.ndarray:
        """Normalized action ``(2,)`` float32 in [-1, 1]: the first control of the solution (or the fallback).

        Raises ``ValueError`` on an observation of the wrong shape or dtype (real numbers only) or with non-finite
        entries.
        """
        scene = self._scene()
        ego, u_prev, ovs, ref = scene.split_obs(scene.check_obs(obs))
        problem = self._problem(scene)
        params = self._params(scene, ego, u_prev, ovs, ref)
        X0, U0 = self._initial_guess(ego, u_prev)
        w0 = np.concatenate([X0.ravel(), U0.ravel(), np.zeros(problem.n_slack)])
        usable, iterate = self._solve(problem, w0, params)
        # Even an unusable iterate (stopped by a cap while still infeasible) is further on than the old guess.
        self._guess = iterate if iterate is not None else (X0, U0)
        if usable:
            self._controls = iterate[1]
            self.plan = (np.vstack([ego, iterate[0]]), iterate[1])
        elif self._controls is not None:
            self._controls = np.vstack([self._controls[1:], self._controls[-1:]])  # the old plan's next control
        if not usable:
            self.failures += 1
        self.step_info = {"status": self._status, "fallback": not usable, "iterations": self._iterations,
                          "slack": self._slack}
        u = self._controls[0] if self._controls is not None else u_prev
        if not np.all(np.isfinite(u)):
            u = u_prev
        return scene.to_normalized(np.clip(u, *scene.actuator_range)).astype(np.float32)

    # --- internals ---------------------------------------------------------------------------------------
    def _initial_guess(self, ego: np.ndarray, u_prev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``X (H, 4)``, ``U (H, 2)``: the previous solution shifted by one step (its last control held and the
        state rolled one step further), or ``u_prev`` held and rolled out from ``ego`` on the first step."""
        H = self.horizon
        if self._guess is None:
            U = np.tile(u_prev, (H, 1))
            X, x = np.empty((H, 4)), ego
            for t in range(H):
                x = np.asarray(self.f(x, U[t])).ravel()
                X[t] = x
            return X, U
        X, U = self._guess
        x_last = np.asarray(self.f(X[-1], U[-1])).ravel()
        return np.vstack([X[1:], x_last]), np.vstack([U[1:], U[-1:]])

    def _solve(self, problem: _Problem, w0: np.ndarray, params: np.ndarray
               ) -> tuple[bool, tuple[np.ndarray, np.ndarray] | None]:
        """Run IPOPT: whether the result may be used, and its iterate ``(X (H, 4), U (H, 2))`` if finite."""
        H = self.horizon
        solver = problem.solver if self._guess is not None else problem.cold_solver
        start = time.perf_counter()
        try:
            out = solver(x0=w0, p=params, lbx=problem.lbx, ubx=problem.ubx, lbg=problem.lbg, ubg=problem.ubg)
            stats = solver.stats()
        except RuntimeError:  # CasADi raises on evaluation errors it cannot hand to IPOPT
            self.statuses["exception"] += 1
            self._status, self._iterations, self._slack = "exception", -1, math.inf
            return False, None
        status = stats.get("return_status", "unknown")
        self.statuses[status] += 1
        self.solve_times.append(time.perf_counter() - start)
        self.iterations.append(int(stats.get("iter_count", -1)))
        self._status, self._iterations = status, self.iterations[-1]
        w = np.asarray(out["x"]).ravel()
        # The largest slack: how far the iterate breaks a softened constraint (0 where it keeps them all).
        self._slack = float(np.max(w[6 * H:], initial=0.0)) if np.all(np.isfinite(w)) else math.inf
        if not np.all(np.isfinite(w)):
            return False, None
        iterate = (w[:4 * H].reshape(H, 4), w[4 * H:6 * H].reshape(H, 2))
        if status in _SUCCESS:
            return True, iterate
        if status not in _CAPPED:
            return False, iterate
        g = np.asarray(out["g"]).ravel()
        violation = max(np.max(problem.lbg - g, initial=0.0), np.max(g - problem.ubg, initial=0.0),
                        np.max(problem.lbx - w, initial=0.0), np.max(w - problem.ubx, initial=0.0))
        if not violation <= self.config.feasibility_tol:
            return False, iterate
        self.capped += 1
        return True, iterate

    def _params(self, scene: Scene, ego, u_prev, ovs, ref) -> np.ndarray:
        """NLP parameters, in the order :meth:`_build` declares them."""
        H = self.horizon
        problem = make_problem(scene, self.config.problem, ego_xy=ego[:2])
        s_o, l_o, v_o, a_o, present = predict_obstacles(problem, ovs, H)
        v_ref, a_ref, lane, _ = reference_profile(problem, ref, ego, H)  # the paper's roads: no lane path
        return np.concatenate([ego, u_prev, lane, v_ref, a_ref, road_params(closed_form(scene)),
                               s_o.ravel(), l_o.ravel(), v_o.ravel(), a_o.ravel(), present.astype(float)])

    def _problem(self, scene: Scene) -> _Problem:
        # The road shape is a parameter; everything else in a scene is fixed per env, so this builds once.
        key = (scene.bounds, scene.dt, scene.vehicle_length, scene.vehicle_width, closed_form(scene).half_width,
               scene.n_obstacles)
        if key not in self._problems:
            self._problems[key] = self._build(scene)
        return self._problems[key]

    def _build(self, scene: Scene) -> _Problem:
        """Formulate eq. 21 (multiple shooting) for ``scene``'s layout and compile IPOPT on it."""
        if self._model_dt is not None and abs(self._model_dt - scene.dt) > 1e-9:
            raise ValueError(f"the dynamics model steps {self._model_dt} s but the scene's dt is {scene.dt} s")
        cfg, H, K = self.config, self.horizon, scene.n_obstacles
        tun = for_road(self.config.problem, scene.bounds.steer, scene.lane_path)  # the road's scales (make_problem's)
        shape, b = tun.barrier, scene.bounds
        X = ca.MX.sym("X", 4, H)  # x_1 .. x_H (columns)
        U = ca.MX.sym("U", 2, H)  # u_0 .. u_{H-1}
        x0, u_prev, ref_lane = ca.MX.sym("x0", 4), ca.MX.sym("u_prev", 2), ca.MX.sym("ref_lane", 1, H + 1)
        v_ref, a_ref = ca.MX.sym("v_ref", 1, H + 1), ca.MX.sym("a_ref", 1, H + 1)
        road = ca.MX.sym("road", len(ROAD_PARAMS))
        # predict_obstacles gives (H + 1, K) arrays, raveled row-major: reshape to (K, H + 1), columns = time.
        s_o, l_o, v_o, a_o = (ca.MX.sym(n, K, H + 1) for n in ("s_o", "l_o", "v_o", "a_o"))
        present = ca.MX.sym("present", K)
        params = [x0, u_prev, ref_lane, v_ref, a_ref, road, s_o, l_o, v_o, a_o, present]
        # ca.vec stacks columns; the numpy side ravels (H + 1, K) row-major, which is the column-major (K, H + 1).
        p = ca.vertcat(*[ca.vec(q) for q in params])

        states = ca.horzcat(x0, X)  # x_0 .. x_H
        s, lat = frenet(states[0, :], states[1, :], road)
        dpsi = states[2, :] - heading_at(s, road)  # the body's: its corners meet the edges
        # x_{t+1}'s course: its heading plus the slip of u_t, the input that reached it (measure's heading row)
        course = dpsi + (ca.horzcat(ca.MX.zeros(1, 1), ca.atan(0.5 * ca.tan(U[1, :]))) if tun.track_course else 0)
        v = states[3, :]
        du = U - ca.horzcat(u_prev, U[:, :-1])

        # Cost (eq. 21, or its Student's-t form): residuals of bimp.planners.problem.measure, weights 1 / sigma^2.
        sr, si, sw = tun.sigma_ref, tun.sigma_input, tun.sigma_du
        q_ref = ((lat - ref_lane) / sr[0]) ** 2 + (course / sr[1]) ** 2 + ((v - v_ref) / sr[2]) ** 2
        # u_t is measured with the state x_{t+1} it reaches, at that state's time (as measure's rows): the
        # feed-forward of the curvature at x_{t+1}, the reference speed's rate at t + 1.
        feedforward = ca.atan(scene.vehicle_length * curvature_at(s[:, 1:], road))
        q_in = ((U[0, :] - a_ref[:, 1:]) / si[0]) ** 2 + ((U[1, :] - feedforward) / si[1]) ** 2
        q_du = (du[0, :] / sw[0]) ** 2 + (du[1, :] / sw[1]) ** 2
        J = ca.sum2(robust_cost(q_ref[:, 1:], 3, tun.nu) + robust_cost(q_in, 2, tun.nu)
                    + robust_cost(q_du, 2, tun.nu))

        # Soft constraints (keep-out and road edges) take a slack each, charged at an exact (L1) penalty: a problem
        # that a sudden brake ahead makes infeasible becomes one that minimizes the violation, and as long as the
        # constraints can be met (and the penalty beats their multipliers) the slack stays 0.
        soft = math.isfinite(cfg.slack_penalty)
        S_edge = ca.MX.sym("S_edge", 1, H) if soft else ca.MX.zeros(1, H)
        S_ov = ca.MX.sym("S_ov", K, H) if soft else ca.MX.zeros(K, H)
        if soft:
            J = J + cfg.slack_penalty * (ca.sum2(S_edge) + ca.sum1(ca.sum2(S_ov)))

        # Constraints: rows over the steps 1..H (inputs and rates: 0..H-1), each with its lower and upper bound.
        g, lbg, ubg = [], [], []

        def add(rows, lower, upper) -> None:
            g.append(ca.vec(rows))
            n = g[-1].shape[0]
            lbg.append(np.broadcast_to(lower, (n,))), ubg.append(np.broadcast_to(upper, (n,)))

        add(self.f.map(H)(states[:, :H], U) - X, 0.0, 0.0)  # multiple shooting
        keep = 1.0 - shape.bound_margin  # hard bounds: HARD_BOUND_MARGIN by default
        rate = np.tile([keep * b.accel_rate, keep * b.steer_rate], H)
        add(du, -rate, rate)
        # Road edges: |l| + L/2 |sin dpsi| + W/2 cos dpsi is the largest of the four corners' +-l +- L/2 sin dpsi
        # + W/2 cos dpsi; four smooth rows instead of one with two kinks.
        half_l, half_w = scene.vehicle_length / 2, scene.vehicle_width / 2
        for sign_l in (1.0, -1.0):
            for sign_h in (1.0, -1.0):
                corner = sign_l * lat[:, 1:] + sign_h * half_l * ca.sin(dpsi[:, 1:]) + half_w * ca.cos(dpsi[:, 1:])
                add(corner - S_edge, -np.inf, closed_form(scene).half_width - shape.edge_margin)
        p_exp = cfg.keep_out_power
        for k in range(K):
            ds = s[:, 1:] - s_o[k, 1:]
            semi_s, semi_l = keep_out_semi_axes(scene, shape, ds, v[:, 1:], v_o[k, 1:], a_o[k, 1:])
            keep_out = (ds / semi_s) ** p_exp + ((lat[:, 1:] - l_o[k, 1:]) / semi_l) ** p_exp - 1.0
            add(keep_out + S_ov[k, :] + (1.0 - present[k]) * _ABSENT, 0.0, np.inf)

        slack = [ca.vec(S_edge), ca.vec(S_ov)] if soft else []
        w = ca.vertcat(ca.vec(X), ca.vec(U), *slack)  # X column-major = x_1, x_2, ... row blocks of 4
        nlp = {"x": w, "p": p, "f": J, "g": ca.vertcat(*g)}

        def solver(name: str, max_iter: int, max_cpu_time: float) -> ca.Function:
            return ca.nlpsol(name, "ipopt", nlp, {"print_time": False, "error_on_fail": False, "ipopt": {
                "print_level": 0, "sb": "yes", "max_iter": max_iter, "max_cpu_time": max_cpu_time,
                "tol": cfg.tol, "acceptable_tol": 1e3 * cfg.tol, "hessian_approximation": cfg.hessian,
                "constr_viol_tol": cfg.feasibility_tol}})

        lo_u = np.array([keep * b.accel[0], -keep * b.steer])
        hi_u = np.array([keep * b.accel[1], keep * b.steer])
        n_slack = (K + 1) * H if soft else 0
        lbx = np.concatenate([np.full(4 * H, -np.inf), np.tile(lo_u, H), np.zeros(n_slack)])
        ubx = np.concatenate([np.full(4 * H, np.inf), np.tile(hi_u, H), np.full(n_slack, np.inf)])
        return _Problem(solver("nmpc", cfg.max_iter, cfg.max_cpu_time),
                        solver("nmpc_cold", cfg.cold_max_iter, cfg.cold_max_cpu_time),
                        lbx, ubx, np.concatenate(lbg), np.concatenate(ubg), n_slack)


def make_nmpc(env, config: str | None = None, **overrides) -> NMPCPlanner:
    """NMPC with the quadratic cost of eq. 21 for ``env``, configured in layers
    (:func:`bimp.planners.problem.load_planner_config`): the shared problem (``configs/problem.yaml``) as
    ``problem`` and :class:`NMPCConfig`'s defaults, NMPC's own problem values (``problem.nu = inf``,
    ``problem.barrier.bound_margin =`` :data:`HARD_BOUND_MARGIN`), the YAML ``config`` on top if given (a file of
    overrides: a key it leaves out keeps its default), then ``overrides`` (``problem=`` a mapping merged key by
    key; an unknown key raises naming it)."""
    nu_inf = {"problem": {"nu": math.inf}}
    return NMPCPlanner(lambda: env.unwrapped.scene,
                       load_planner_config(NMPCConfig, HARD_BOUNDS, nu_inf, config, overrides))


def make_nmpc_t(env, config: str | None = None, **overrides) -> NMPCPlanner:
    """NMPC with the Student's-t log cost of section IV, ``problem.nu`` the shared problem's (EnKTS's); configured
    in layers as :func:`make_nmpc`. ``bimp.agents.make_policy("nmpc-t", ...)`` starts from the shipped tuned config
    (``configs/tuned/nmpc-t.yaml``) instead."""
    return NMPCPlanner(lambda: env.unwrapped.scene, load_planner_config(NMPCConfig, HARD_BOUNDS, config, overrides))


def search_space() -> dict:
    """What ``bimp tune`` searches for NMPC: the weights of its cost and the margins of its constraints
    (``problem.*``), the keep-out's shape and the slack penalty. Not the
    iteration cap: it buys quality with compute, compared across values by ``bimp frontier``."""
    from optuna.distributions import CategoricalDistribution
    from optuna.distributions import FloatDistribution as Float

    return {
        **problem_search_space(),
        "keep_out_power": CategoricalDistribution([2, 4, 6]),
        "slack_penalty": Float(1e2, 1e5, log=True),
    }


def nmpc_t_search_space() -> dict:
    """NMPC's search space and the Student's-t cost's nu."""
    from optuna.distributions import FloatDistribution as Float

    return {**search_space(), "problem.nu": Float(2.5, 30.0, log=True)}


__all__ = ["HARD_BOUND_MARGIN", "NMPCConfig", "NMPCPlanner", "make_nmpc", "make_nmpc_t", "mlp_function",
           "bicycle_function", "frenet", "keep_out_semi_axes", "nmpc_t_search_space", "robust_cost", "search_space"]
