"""bimp.planners.nmpc: the CasADi pieces against their numpy originals (MLP, Frenet frame, keep-out semi-axes), the
compiled NLP's road-edge rows and cost against planners.problem (edge distance, measure's tracking rows), known
optima of toy instances (quadratic and Student's-t cost, interior and active bounds), failure fallbacks, the
Policy contract on both scenarios, config validation."""

from __future__ import annotations

import dataclasses
import math

import casadi as ca
import gymnasium as gym
import numpy as np
import pytest

from bimp import envs
from bimp.configs import ConfigError
from bimp.envs.road import RoadGeometry
from bimp.envs.scene import Bounds, Scene
from bimp.planners.dynamics import BicycleModel, load_model, save_model
from bimp.planners.nmpc import (
    HARD_BOUND_MARGIN,
    NMPCConfig,
    NMPCPlanner,
    bicycle_function,
    curvature_at,
    frenet,
    heading_at,
    keep_out_semi_axes,
    make_nmpc,
    make_nmpc_t,
    mlp_function,
    road_params,
    robust_cost,
)
from bimp.planners.problem import (
    N_TRACK,
    BarrierShape,
    ProblemConfig,
    edge_distance_local,
    load_problem,
    make_problem,
    measure,
    predict_obstacles,
    reference_profile,
)

DT = 0.1


def nmpc(horizon: int, problem: ProblemConfig = ProblemConfig(), nu: float = math.inf, **config) -> NMPCConfig:
    """An NMPCConfig on ``problem`` at ``horizon``, with NMPC's own nu (``inf``: the quadratic cost) and hard-bound
    margin, as :func:`make_nmpc` sets them over the shared problem."""
    barrier = dataclasses.replace(problem.barrier, bound_margin=HARD_BOUND_MARGIN)
    return NMPCConfig(problem=dataclasses.replace(problem, horizon=horizon, nu=nu, barrier=barrier), **config)


def toy_scene() -> Scene:
    straight = RoadGeometry(arc_angle=0.0)
    return Scene(road=straight.route(), geometry=straight, bounds=Bounds(), dt=DT, vehicle_length=5.0,
                 vehicle_width=2.0,
                 actuator_accel=(-10.0, 10.0), actuator_steer=(-0.3, 0.3), n_obstacles=2)


def toy_dynamics() -> ca.Function:
    """Speed integrates the acceleration, the position the speed; steering moves nothing: a linear model whose
    H = 1 optimum is a scalar least-squares problem per input."""
    x, u = ca.MX.sym("x", 4), ca.MX.sym("u", 2)
    return ca.Function("toy", [x, u], [ca.vertcat(x[0] + x[3] * DT, x[1], x[2], x[3] + u[0] * DT)])


def toy_obs(scene: Scene, v0: float, u_prev, v_ref: float, ovs=None) -> np.ndarray:
    lane = float(scene.geometry.lane_offset(1))
    ov_rows = np.zeros((2, 6)) if ovs is None else np.asarray(ovs, float)
    return np.concatenate([[0.0, lane, 0.0, v0], u_prev, ov_rows.ravel(), [v_ref, 0.0, lane]])


@pytest.fixture(scope="module")
def model():
    return load_model()


def test_casadi_mlp_equals_learned_dynamics(model):
    rng = np.random.default_rng(0)
    n = 300
    x = np.column_stack([rng.uniform(-300, 300, n), rng.uniform(-10, 10, n), rng.uniform(-4, 4, n),
                         rng.uniform(0, 42, n)])  # speeds past max_speed too: the acceleration cap
    x[::7, 3] = 0.0  # at rest, braking: the speed clamp
    u = np.column_stack([rng.uniform(-12, 12, n), rng.uniform(-0.4, 0.4, n)])  # beyond the actuators: clipping
    got = np.asarray(mlp_function(model).map(n)(x.T, u.T)).T
    # predict runs the net in float32: agreement to float32 rounding of a step's change (metres, rad, m/s)
    np.testing.assert_allclose(got, model.predict(x, u), rtol=0, atol=1e-5)


def test_casadi_bicycle_equals_bicycle_model():
    rng = np.random.default_rng(5)
    n = 300
    x = np.column_stack([rng.uniform(-300, 300, n), rng.uniform(-10, 10, n), rng.uniform(-4, 4, n),
                         rng.uniform(0, 42, n)])
    x[::7, 3] = 0.0
    u = np.column_stack([rng.uniform(-12, 12, n), rng.uniform(-0.4, 0.4, n)])
    for bicycle in (BicycleModel(), BicycleModel(clip_inputs=False)):
        got = np.asarray(bicycle_function(bicycle).map(n)(x.T, u.T)).T
        np.testing.assert_allclose(got, bicycle.predict(x, u), rtol=0, atol=1e-12)


def test_default_dynamics_follow_the_problem_key(model, tmp_path):
    copy = save_model(model, tmp_path / "copy.pt")
    rng = np.random.default_rng(6)
    x = np.column_stack([rng.uniform(-50, 50, (20, 2)), rng.uniform(-1, 1, 20), rng.uniform(0, 35, 20)])
    u = np.column_stack([rng.uniform(-8, 3, 20), rng.uniform(-0.2, 0.2, 20)])
    shipped = np.asarray(mlp_function(model).map(20)(x.T, u.T)).T
    for name, expected in ((str(copy), shipped), ("mlp", shipped)):
        planner = NMPCPlanner(toy_scene(), nmpc(2, ProblemConfig(dynamics=name)))
        np.testing.assert_array_equal(np.asarray(planner.f.map(20)(x.T, u.T)).T, expected)
    planner = NMPCPlanner(toy_scene(), nmpc(2, ProblemConfig(dynamics="bicycle")))
    np.testing.assert_allclose(np.asarray(planner.f.map(20)(x.T, u.T)).T, BicycleModel()(x, u), atol=1e-12)


@pytest.mark.parametrize("arc_deg", [60.0, -45.0, 0.0])
def test_casadi_frenet_heading_and_curvature_match_the_road(arc_deg):
    road = RoadGeometry(straight_in=100.0, radius=200.0, arc_angle=math.radians(arc_deg), straight_out=300.0)
    rng = np.random.default_rng(1)
    s = rng.uniform(-20, road.length, 400)
    lat = rng.uniform(-6, 6, 400)
    xy = road.position(s, lat)
    X, P = ca.SX.sym("X", 2, 400), ca.SX.sym("p", 3)
    fs, fl = frenet(X[0, :], X[1, :], P)
    f = ca.Function("f", [X, P], [fs, fl, heading_at(fs, P), curvature_at(fs, P)])
    got = [np.asarray(v).ravel() for v in f(xy.T, road_params(road))]
    s_np, l_np = road.to_frenet(xy)
    np.testing.assert_allclose(got[0], s_np, atol=1e-9)
    np.testing.assert_allclose(got[1], l_np, atol=1e-9)
    np.testing.assert_allclose(got[2], road.heading_at(s_np), atol=1e-12)
    inside = np.abs(s_np - road.straight_in) > 1e-6  # the arc's end points are a tie either way
    np.testing.assert_allclose(got[3][inside], road.curvature_at(s_np)[inside], atol=1e-12)


def curved_nlp(horizon: int, seed: int, ref=None, **problem):
    """An NMPC planner on overtaking with the scenarios' sharpest curve (R = 180 m), its compiled NLP and the NLP
    parameters of the first observation (``ref`` replaces the observed reference; ``problem``: keys of its
    :class:`ProblemConfig`)."""
    env = gym.make(envs.env_id("overtaking"), config={"radius": 180.0})
    obs, _ = env.reset(seed=seed)
    scene = env.unwrapped.scene
    assert scene.geometry.radius == 180.0 and scene.geometry.arc_angle != 0
    planner = NMPCPlanner(scene, nmpc(horizon, ProblemConfig(dynamics="bicycle", **problem)))
    ego, u_prev, ovs, obs_ref = scene.split_obs(obs)
    params = planner._params(scene, ego, u_prev, ovs, obs_ref if ref is None else np.asarray(ref, float))
    return scene, planner, planner._problem(scene), params, (ego, u_prev, ovs)


def random_states_near_the_road(scene: Scene, rng, n: int) -> np.ndarray:
    """``(n, 4)`` states over the whole road (straights and arc), centres up to 1 m past the edges, headings
    within 0.1 rad of the road's."""
    s = rng.uniform(0, scene.geometry.length, n)
    lat = rng.uniform(-scene.geometry.half_width - 1, scene.geometry.half_width + 1, n)
    return np.column_stack([scene.geometry.position(s, lat), scene.geometry.heading_at(s) + rng.uniform(-0.1, 0.1, n),
                            rng.uniform(0, 30, n)])


def test_road_edge_rows_are_the_problem_edge_distance():
    """NMPC's four smooth corner rows, evaluated in its compiled NLP (CasADi Frenet frame included), give
    ``bimp.planners.problem.edge_distance_local`` (the planners' edge distance) and are bounded at the barrier's edge
    margin. That local distance is within 2 cm of the exact corners (``edge_distance``) on the scenarios' sharpest
    curve: it takes the road as straight over the car, and the road bends by (L/2)^2 / 2R = 1.7 cm over half a
    5 m car at R = 180 m (so a 1 mm bound does not hold; the margin is 0.3 m). The env's edge distance is the
    problem's exact one."""
    H, n_batches = 10, 30
    scene, planner, nlp, params, _ = curved_nlp(H, seed=3)
    problem = make_problem(scene, planner.config.problem)
    hw = scene.geometry.half_width
    g = nlp.solver.get_function("nlp_g")
    rows = slice(6 * H, 10 * H)  # after the shooting (4 H) and rate (2 H) rows: four corner blocks of H
    np.testing.assert_allclose(nlp.ubg[rows], scene.geometry.half_width - planner.config.problem.barrier.edge_margin)
    assert np.all(nlp.lbg[rows] == -np.inf)
    rng = np.random.default_rng(4)
    x = random_states_near_the_road(scene, rng, H * n_batches)
    for X in x.reshape(n_batches, H, 4):
        w = np.concatenate([X.ravel(), np.zeros(2 * H + nlp.n_slack)])  # inputs and slack 0: the bare rows
        corners = np.asarray(g(w, params)).ravel()[rows].reshape(4, H)
        s_f, l_f = scene.geometry.to_frenet(X[:, :2])  # NMPC's road: the closed form
        dpsi = X[:, 2] - scene.geometry.heading_at(s_f)
        local = edge_distance_local(-hw, hw, problem.limits, l_f, dpsi)
        np.testing.assert_allclose(scene.geometry.half_width - corners.max(axis=0), local, rtol=0, atol=1e-9)
    s_f, l_f = scene.geometry.to_frenet(x[:, :2])
    local = edge_distance_local(-hw, hw, problem.limits, l_f, x[:, 2] - scene.geometry.heading_at(s_f))
    exact = scene.edge_distance(x)  # the exact corners, as the env measures them
    assert np.any(np.abs(local - exact) > 0.01)  # the curve's bend is there, and bounded:
    np.testing.assert_allclose(local, exact, rtol=0, atol=0.02)
    g_ = scene.geometry
    on_straights = (s_f < g_.straight_in - 3) | (s_f > g_.straight_in + g_.arc_length + 3)
    assert on_straights.sum() > 50
    np.testing.assert_allclose(local[on_straights], exact[on_straights], rtol=0, atol=1e-9)  # exact where straight


@pytest.mark.parametrize("track_course", [False, True])
def test_cost_is_the_nll_of_the_problem_tracking_rows(track_course):
    """With ``nu = inf`` NMPC's cost is the NLL of ``measure``'s tracking rows (reference state and input) of the
    states ``x_1 .. x_H``, each with the input ``u_t`` that reached it and the references of its own time
    ``t + 1`` (the curvature feed-forward at ``x_{t+1}``, the reference speed's rate at ``t + 1``; the course
    with ``u_t``'s slip where the heading row tracks the course), plus the increments' prior
    ``|u_t - u_{t-1}|^2_{Sigma_w^-1} / 2``. A reference speed braking to 0 inside the horizon makes its rate change
    with t; random states over the curve make the feed-forward change."""
    H = 6
    ref_lane = 2.0
    scene, planner, nlp, params, (ego, u_prev, ovs) = curved_nlp(H, seed=5, ref=[0.5, -2.0, ref_lane],
                                                                 track_course=track_course)
    tun = planner.config.problem
    # The whole road in one window (the states are drawn over all of it).
    problem = make_problem(scene, dataclasses.replace(tun, road_points=1500))
    v_ref, a_ref, lane, _ = reference_profile(problem, np.array([0.5, -2.0, ref_lane]), ego, H)
    assert len(set(a_ref.tolist())) == 2  # the rate switches to 0 where the reference stops
    s_o, l_o, v_o, a_o, present = predict_obstacles(problem, ovs, H)
    f = nlp.solver.get_function("nlp_f")
    rng = np.random.default_rng(6)
    for _ in range(10):
        X = random_states_near_the_road(scene, rng, H)
        U = np.column_stack([rng.uniform(-6, 3, H), rng.uniform(-0.3, 0.3, H)])  # slips up to 0.15 rad
        du = U - np.vstack([u_prev, U[:-1]])
        expected = 0.5 * np.sum((du / tun.sigma_du) ** 2)
        for t in range(H):
            h = measure(problem, X[t:t + 1], U[t:t + 1], du[t:t + 1], U[:1], u_prev, lane[t + 1], v_ref[t + 1],
                        a_ref[t + 1], (s_o[t + 1], l_o[t + 1], v_o[t + 1], a_o[t + 1], present))
            expected += 0.5 * np.sum((h[0, :N_TRACK] / problem.noise[:N_TRACK]) ** 2)
        got = float(f(np.concatenate([X.ravel(), U.ravel(), np.zeros(nlp.n_slack)]), params))  # no slack used
        # NMPC's road is the closed form, measure's the polyline sampled from it: equal to its millimetre.
        assert got == pytest.approx(expected, rel=1e-4)


def test_keep_out_semi_axes_are_those_of_the_virtual_barrier():
    """Where ``measure``'s OV barrier reads a given penetration, the NMPC's semi-axes say the same: invert the
    softplus hinge to get phi = 1 - |ds| / semi_s (dl = 0) or 1 - |dl| / semi_l (ds = 0)."""
    env = gym.make(envs.env_id("overtaking"))
    env.reset(seed=3)
    scene, shape = env.unwrapped.scene, BarrierShape()
    problem = make_problem(scene, ProblemConfig(barrier=shape, road_points=1500))  # the whole road in one window
    rng = np.random.default_rng(2)
    n = 64
    v, v_o = rng.uniform(0, 30, n), rng.uniform(0, 30, n)
    a_o = np.where(np.arange(n) % 2 == 0, rng.uniform(-8, -0.6, n), 0.0)  # braking leaders and steady ones
    sign = np.where(np.arange(n) % 4 < 2, -1.0, 1.0)  # behind and ahead of the OV
    semi = ca.Function("semi", [sym := ca.SX.sym("q", 4)], list(keep_out_semi_axes(scene, shape, *ca.vertsplit(sym))))
    semi_s = np.array([float(semi([sign[i], v[i], v_o[i], a_o[i]])[0]) for i in range(n)])
    semi_l = float(semi([1.0, 1.0, 1.0, 0.0])[1])
    s_o, lane = 150.0, float(scene.geometry.lane_offset(1))
    zeros = np.zeros((1, 2))
    for ds, dl in ((0.9 * sign * semi_s, np.zeros(n)), (np.zeros(n), np.full(n, 0.9 * semi_l))):
        xy = scene.geometry.position(s_o + ds, lane + dl)
        x = np.column_stack([xy, scene.geometry.heading_at(s_o + ds), v])
        phi = np.empty(n)
        for i in range(n):  # one OV (the second slot absent), its own speed and acceleration per row
            ov = (np.array([s_o, 0.0]), np.array([lane, 0.0]), np.array([v_o[i], 0.0]), np.array([a_o[i], 0.0]),
                  np.array([True, False]))
            h = measure(problem, x[i:i + 1], zeros, zeros, zeros, np.zeros(2), lane, 20.0, 0.0, ov)
            phi[i] = shape.widths[0] * np.log(np.expm1(shape.sharpness * h[0, N_TRACK])) / shape.sharpness
        # 1 - 0.9: both agree on where the keep-out ends (to the polyline's millimetre over semi-axes of metres)
        np.testing.assert_allclose(phi, 0.1, atol=1e-3)


def solve_toy(tuning: ProblemConfig, obs: np.ndarray, nu: float = math.inf, **config) -> tuple[NMPCPlanner, np.ndarray]:
    scene = toy_scene()
    planner = NMPCPlanner(scene, nmpc(1, tuning, nu, tol=1e-10, **config), toy_dynamics())
    action = planner.act(obs)
    return planner, scene.to_physical(action)


def test_quadratic_toy_matches_the_closed_form_optimum():
    tuning = ProblemConfig()
    v0, v_ref, u_prev = 20.0, 25.0, np.array([0.5, 0.01])
    planner, u = solve_toy(tuning, toy_obs(toy_scene(), v0, u_prev, v_ref))
    (_, _, sv), (sa, sd), (swa, swd) = tuning.sigma_ref, tuning.sigma_input, tuning.sigma_du
    # J(a) = [(v0 + a dt - v_ref)^2 / sv^2 + a^2 / sa^2 + (a - a_prev)^2 / swa^2] / 2, the same for delta
    # (feed-forward 0 on a straight road, heading untouched by the toy's steering).
    a_star = (DT * (v_ref - v0) / sv**2 + u_prev[0] / swa**2) / (DT**2 / sv**2 + 1 / sa**2 + 1 / swa**2)
    d_star = (u_prev[1] / swd**2) / (1 / sd**2 + 1 / swd**2)
    b = toy_scene().bounds
    assert abs(a_star - u_prev[0]) < b.accel_rate and abs(d_star - u_prev[1]) < b.steer_rate  # interior optimum
    assert planner.statuses["Solve_Succeeded"] == 1 and planner.failures == 0
    np.testing.assert_allclose(u, [a_star, d_star], rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("a_prev, expected", [(0.0, 0.999), (2.5, 3.0 * 0.999)])
def test_quadratic_toy_stops_on_the_rate_or_input_bound(a_prev, expected):
    """A loose rate prior and a tight speed target want a large acceleration: the optimum of a convex scalar
    problem is then the bound it hits (the rate bound from 0, the input bound from 2.5), tightened by 1e-3."""
    tuning = ProblemConfig(sigma_du=(50.0, 0.002), sigma_ref=(1.0, 0.05, 0.1))
    planner, u = solve_toy(tuning, toy_obs(toy_scene(), 10.0, np.array([a_prev, 0.0]), 30.0))
    b = toy_scene().bounds
    assert planner.failures == 0
    assert u[0] == pytest.approx(expected, abs=1e-6)
    assert b.accel[0] <= u[0] <= b.accel[1] and abs(u[0] - a_prev) <= b.accel_rate and abs(u[1]) <= b.steer
    X, U = planner.plan
    np.testing.assert_allclose(X[1, 3], 10.0 + U[0, 0] * DT, atol=1e-9)  # the dynamics hold


def test_student_t_toy_matches_a_grid_search():
    tuning = ProblemConfig()
    nu, v0, v_ref, u_prev = tuning.nu, 20.0, 24.0, np.array([0.3, 0.004])
    _, u = solve_toy(tuning, toy_obs(toy_scene(), v0, u_prev, v_ref), nu=nu)
    (_, _, sv), (sa, sd), (swa, swd) = tuning.sigma_ref, tuning.sigma_input, tuning.sigma_du

    def cost(a, d):
        rho = lambda q, n: (nu + n) / 2 * np.log1p(q / nu)  # noqa: E731 - section IV's log cost
        return (rho(((v0 + a * DT - v_ref) / sv) ** 2, 3) + rho((a / sa) ** 2 + (d / sd) ** 2, 2)
                + rho(((a - u_prev[0]) / swa) ** 2 + ((d - u_prev[1]) / swd) ** 2, 2))

    a, d = u_prev
    for half in (0.5, 0.02, 1e-3, 5e-5):  # zooming grid search around the best point so far
        A, D = np.meshgrid(a + np.linspace(-half, half, 201), d + np.linspace(-half, half, 201) * 0.01)
        k = np.argmin(cost(A, D))
        a, d = A.flat[k], D.flat[k]
    assert u[0] == pytest.approx(a, abs=1e-5) and u[1] == pytest.approx(d, abs=1e-6), (u, a, d)
    assert robust_cost(4.0, 2, math.inf) == 2.0
    assert float(robust_cost(4.0, 2, 1e9)) == pytest.approx(2.0, rel=1e-6)


def test_infeasible_problem_falls_back_and_counts():
    scene = toy_scene()
    hard = nmpc(3, max_iter=50, cold_max_iter=50, slack_penalty=math.inf)
    planner = NMPCPlanner(scene, hard, toy_dynamics())
    u_prev = np.array([-1.0, 0.002])
    lane = float(scene.geometry.lane_offset(1))
    blocked = [[1.0, 1.0, lane, 0.0, 20.0, 0.0], [0.0] * 6]  # an OV 1 m ahead: every plan is inside its keep-out
    action = planner.act(toy_obs(scene, 20.0, u_prev, 20.0, blocked))
    assert planner.failures == 1 and np.all(np.isfinite(action))
    np.testing.assert_allclose(scene.to_physical(action), u_prev, atol=1e-6)  # no plan yet: hold the last input

    planner.reset()
    planner.act(toy_obs(scene, 20.0, u_prev, 25.0))
    assert planner.failures == 1
    plan_controls = planner.plan[1].copy()
    action = planner.act(toy_obs(scene, 20.0, plan_controls[0], 25.0, blocked))
    assert planner.failures == 2
    np.testing.assert_allclose(scene.to_physical(action), plan_controls[1], atol=1e-6)  # the plan's next control


def test_soft_constraints_turn_an_infeasible_problem_into_the_least_violation():
    # An OV 10 m ahead at the EV's speed: inside the keep-out (headway and braking room) whatever the plan does in
    # 0.3 s. Hard constraints: infeasible, the action falls back (holds the input). Soft: brake at the rate bound.
    scene = toy_scene()
    lane = float(scene.geometry.lane_offset(1))
    obs = toy_obs(scene, 20.0, np.array([0.0, 0.0]), 20.0, [[1.0, 10.0, lane, 0.0, 20.0, 0.0], [0.0] * 6])
    actions = {}
    for penalty in (math.inf, 1e4):
        planner = NMPCPlanner(scene, nmpc(3, max_iter=100, cold_max_iter=100, slack_penalty=penalty), toy_dynamics())
        actions[penalty] = scene.to_physical(planner.act(obs))
        assert planner.step_info["fallback"] == math.isinf(penalty), planner.step_info
    assert actions[math.inf][0] == pytest.approx(0.0, abs=1e-6)
    assert actions[1e4][0] == pytest.approx(-Bounds().accel_rate, rel=0.01)


def test_iteration_cap_uses_a_feasible_iterate():
    scene = toy_scene()
    planner = NMPCPlanner(scene, nmpc(3, cold_max_iter=0), toy_dynamics())
    action = planner.act(toy_obs(scene, 20.0, np.array([0.5, 0.0]), 25.0))
    assert planner.statuses["Maximum_Iterations_Exceeded"] == 1 and planner.capped == 1 and planner.failures == 0
    np.testing.assert_allclose(scene.to_physical(action), [0.5, 0.0], atol=1e-3)  # the initial guess holds u_prev


@pytest.mark.parametrize("scenario, factory", [("overtaking", make_nmpc), ("emergency-brake", make_nmpc),
                                               ("overtaking", make_nmpc_t)])
def test_actions_are_finite_and_in_the_action_space(scenario, factory):
    env = gym.make(envs.env_id(scenario))
    obs, _ = env.reset(seed=0)
    planner = factory(env)
    planner.reset(0)
    for _ in range(3):
        action = planner.act(obs)
        assert action.dtype == np.float32 and action.shape == (2,) and env.action_space.contains(action)
        obs, *_ = env.step(action)
    # (failures are not asserted: a cold first solve may hit the CPU-time cap on a loaded machine)
    assert sum(planner.statuses.values()) == 3
    if factory is make_nmpc_t:
        assert planner.config.problem.nu == load_problem().nu


@pytest.mark.parametrize("policy", ["nmpc", "nmpc-t"])
def test_a_highway_env_road_is_refused_when_the_policy_is_built_not_in_its_episodes(policy, tmp_path):
    from bimp.agents.commands.evaluate import main as evaluate_main
    from bimp.agents.registry import make_policy

    with pytest.raises(ValueError, match="closed-form road"):
        make_policy(policy, gym.make(envs.env_id("stalled-vehicle")))
    assert evaluate_main(["--scenario", "stalled-vehicle", "--policy", policy, "--episodes", "1",
                          "--out", str(tmp_path / "out")]) == 2
    assert not (tmp_path / "out" / "episodes.jsonl").exists()
    make_policy(policy, gym.make(envs.env_id("overtaking-noisy")))  # the paper's road under noise: planned on


def test_config_validation_and_unknown_overrides():
    for bad in ({"problem": {"horizon": 0}}, {"problem": {"nu": 0.0}}, {"max_iter": -1}, {"hessian": "bfgs"},
                {"keep_out_power": 3}, {"problem": {"barrier": {"bound_margin": 1.0}}}, {"max_cpu_time": 0.0},
                {"cold_max_iter": -1}, {"cold_max_cpu_time": 0.0}):
        with pytest.raises(ValueError):
            NMPCConfig(**bad)
    env = gym.make(envs.env_id("overtaking"))
    with pytest.raises(ValueError, match="max_iters"):
        make_nmpc(env, max_iters=5)
    assert make_nmpc(env, problem={"horizon": 7}).horizon == 7


@pytest.mark.parametrize("old, new", [("horizon", "problem.horizon"), ("nu", "problem.nu"),
                                      ("bound_tightening", "problem.barrier.bound_margin")])
def test_the_old_keys_are_refused_naming_the_new_one(old, new):
    env = gym.make(envs.env_id("overtaking"))
    for factory in (make_nmpc, make_nmpc_t):
        with pytest.raises(ValueError, match=f"{old} is now {new}"):
            factory(env, **{old: 7})


def test_nmpc_keeps_its_own_nu_and_hard_bound_margin_over_the_shared_problem():
    """One name each: what were NMPCConfig.nu and .bound_tightening are the problem's nu and bound_margin, at the
    values NMPC had (nu inf for nmpc, the shared problem's for nmpc-t; a 1e-3 margin on its hard bounds)."""
    env = gym.make(envs.env_id("overtaking"))
    shared = load_problem()
    nmpc_, nmpc_t = make_nmpc(env).config.problem, make_nmpc_t(env).config.problem
    assert math.isinf(nmpc_.nu) and nmpc_t.nu == shared.nu
    assert nmpc_.barrier.bound_margin == nmpc_t.barrier.bound_margin == HARD_BOUND_MARGIN == 1e-3
    assert NMPCConfig().problem.barrier.bound_margin == HARD_BOUND_MARGIN and math.isinf(NMPCConfig().problem.nu)
    assert dataclasses.replace(nmpc_t, barrier=shared.barrier) == shared  # nothing else differs
    assert make_nmpc(env, problem={"nu": 5.0}).config.problem.nu == 5.0


def test_the_episode_record_marks_each_forced_solver_failure(tmp_path):
    # No iterations allowed and an infeasible first guess: every solve stops at the cap, infeasible -> fallback.
    from bimp.agents.evaluation.evaluate import evaluate, read_records

    evaluate(["emergency-brake"], ["nmpc"], 1, 3, out=tmp_path, traces=1, progress=False,
             overrides={"nmpc": {"max_iter": 0, "cold_max_iter": 0, "problem.horizon": 3}})
    (record,) = read_records(tmp_path)
    infos = record["trace"]["policy_info"]
    assert len(infos) == record["steps"]
    forced = [i for i, info in enumerate(infos) if info["status"] == "Maximum_Iterations_Exceeded" and info["fallback"]]
    assert forced and record["policy_info"]["fallback_steps"] == [i for i, info in enumerate(infos) if info["fallback"]]
    assert record["policy_info"]["slack"]["max"] >= 0.0  # the largest slack of a solve, recorded
    assert sum(record["policy_info"]["status"].values()) == record["steps"]


def test_nu_below_the_float32_floor_is_refused_naming_nu():
    """The same floor as the shared problem's nu (bimp.planners.problem.NU_MIN), which nmpc-t takes."""
    for nu in (2.000000000001, 1.0):
        with pytest.raises(ConfigError, match="nu") as err:
            NMPCConfig(problem={"nu": nu})
        assert err.value.key == "problem.nu"
    assert NMPCConfig(problem={"nu": 2.1}).problem.nu == 2.1
