"""bimp.planners.problem: the one definition of the planning problem, in numpy and JAX alike, and the env's agreement
with it."""

import dataclasses

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bimp import envs  # noqa: F401  (registers the envs)
from bimp.envs.scene import BOUND_CONSTRAINTS, bound_constraints
from bimp.planners.problem import (
    N_FIRST_CONTROL,
    STEER_UNIT,
    BarrierShape,
    ProblemConfig,
    for_road,
    load_problem,
    make_problem,
    measure,
    measurement_noise,
    predict_obstacles,
    reference_profile,
    road_changes,
)


@pytest.fixture
def scene():
    env = gym.make("bimp/EmergencyBrake-v0")
    env.reset(seed=0)
    return env.unwrapped.scene


@pytest.fixture
def problem(scene):
    return make_problem(scene, ProblemConfig())


def test_obstacles_brake_to_a_stop_and_stay_there(problem):
    ovs = np.array([[1.0, 50.0, 2.0, 0.0, 10.0, -5.0], [1.0, 80.0, -2.0, 0.0, 20.0, 0.0]])
    s, lat, v, a, present = predict_obstacles(problem, ovs, horizon=30)
    assert s.shape == v.shape == a.shape == lat.shape == (31, 2) and present.all()
    np.testing.assert_allclose(v[:, 0], np.maximum(10.0 - 5.0 * 0.1 * np.arange(31), 0.0))
    np.testing.assert_allclose(s[-1, 0], 50.0 + 10.0**2 / (2 * 5.0))  # stopped after 2 s, 10 m on
    assert np.all(a[20:, 0] == 0.0) and np.all(a[:20, 0] == -5.0)
    np.testing.assert_allclose(s[:, 1], 80.0 + 20.0 * 0.1 * np.arange(31))
    np.testing.assert_allclose(lat, [[2.0, -2.0]] * 31)


def test_reference_profile_never_negative(problem):
    v, a, _, _ = reference_profile(problem, np.array([2.0, -5.0, 2.0]), np.array([0.0, 2.0, 0.0, 2.0]), horizon=10)
    np.testing.assert_allclose(v, np.maximum(2.0 - 0.5 * np.arange(11), 0.0))
    assert np.all(a[v == 0] == 0.0) and a[0] == -5.0


def test_measurement_reads_zero_on_the_reference_and_flags_each_constraint(problem):
    far = (np.array([500.0, 500.0]), np.array([2.0, -2.0]), np.array([20.0, 20.0]), np.zeros(2),
           np.ones(2, bool))
    x = np.array([[10.0, 2.0, 0.0, 20.0]])
    zero_u = np.zeros((1, 2))
    h = measure(problem, x, zero_u, zero_u, zero_u, np.zeros(2), 2.0, 20.0, 0.0, far)
    assert h.shape == (1, len(problem.noise)) == (1, 16)  # tracking (5), one barrier per OV, nine more
    np.testing.assert_allclose(h[0, :5], 0.0, atol=1e-12)
    assert np.all(h[0, 5:] < 1e-3)

    near = (np.array([14.0, 500.0]), np.array([2.0, -2.0]), np.array([20.0, 20.0]), np.zeros(2), np.ones(2, bool))
    h_near = measure(problem, x, zero_u, zero_u, zero_u, np.zeros(2), 2.0, 20.0, 0.0, near)
    assert h_near[0, 5] > 1.0 and h_near[0, 6] < 1e-3  # OV1 right ahead in the lane; OV2 far

    off_edge = np.array([[10.0, 3.9, 0.0, 20.0]])
    bad_u = np.array([[-9.0, 0.2]])
    h_bad = measure(problem, off_edge, bad_u, bad_u, bad_u, np.zeros(2), 2.0, 20.0, 0.0, far)
    assert np.all(h_bad[0, 7:] > 1.0)  # edge, both bounds, both rates, and the four first-control barriers


def test_numpy_and_jax_give_the_same_measurement(problem):
    rng = np.random.default_rng(0)
    x = np.column_stack([rng.uniform(0, 60, 20), rng.uniform(-4, 4, 20), rng.uniform(-0.1, 0.1, 20),
                         rng.uniform(0, 30, 20)])
    u, du, u0 = (rng.normal(0, s, (20, 2)) * [1, 0.01] for s in (3.0, 1.0, 3.0))
    ovs = np.array([[1.0, 50.0, 2.0, 0.0, 10.0, -5.0], [1.0, 30.0, -2.0, 0.0, 20.0, 0.0]])
    obst = predict_obstacles(problem, ovs, 5)
    args = (u, du, u0, np.array([0.5, 0.001]), 2.0, 20.0, -1.0)
    h_np = measure(problem, x, *args, tuple(a[3] for a in obst[:4]) + (obst[4],))
    p32 = jax.tree.map(lambda a: jnp.asarray(a, jnp.float32), problem)
    obst_j = predict_obstacles(p32, jnp.asarray(ovs, jnp.float32), 5)
    h_jax = jax.jit(lambda p, x: measure(p, x, *args, tuple(a[3] for a in obst_j[:4]) + (obst_j[4],)))(p32, x)
    np.testing.assert_allclose(np.asarray(h_jax), h_np, rtol=2e-3, atol=2e-4)


def test_the_env_reports_the_input_and_rate_constraints_the_problem_measures():
    """Eq. 4-5 have one definition (bimp.envs.scene.bound_constraints): on the states and inputs of an episode driven
    by random actions (many beyond the bounds), the env's ``info["constraints"]`` are its values on the problem's
    limits, bit for bit, and the problem's barrier rows (bounds untightened) are the softplus of those same numbers,
    for the step's input and for the first control. A second copy of the bounds on either side breaks it."""
    env = gym.make("bimp/Overtaking-v0")
    obs, info = env.reset(seed=4)
    scene = env.unwrapped.scene
    problem = make_problem(scene, ProblemConfig(barrier=BarrierShape(bound_margin=0.0)))
    bar, far = problem.barrier, (np.full(2, 1e4), np.zeros(2), np.zeros(2), np.zeros(2), np.zeros(2, bool))
    rng = np.random.default_rng(1)
    for _ in range(25):
        prev = np.asarray(info["input"])  # the input applied last, in float64 (the observation's is float32)
        obs, _, terminated, truncated, info = env.step(rng.uniform(-1, 1, 2).astype(np.float32) * [0.9, 0.25])
        u = np.asarray(info["input"])[None]
        reported = np.array([[info["constraints"][key] for key in BOUND_CONSTRAINTS]])
        np.testing.assert_array_equal(bound_constraints(problem.limits, u, u - prev), reported)

        x = scene.split_obs(obs)[0][None]
        h = measure(problem, x, u, u - prev, u, prev, 0.0, 0.0, 0.0, far)
        phi = np.column_stack([reported[:, :2].max(axis=1), reported[:, 2:]]) / bar.widths[2:6]
        psi = np.logaddexp(0.0, bar.sharpness * phi) / bar.sharpness
        np.testing.assert_allclose(h[:, -2 * N_FIRST_CONTROL:], np.hstack([psi, psi]), rtol=1e-12, atol=0)
        if terminated or truncated:
            break


def test_the_shared_tuning_loads_and_is_what_every_planner_reads():
    shared = load_problem()
    assert shared.horizon == 20 and shared.nu == 4.0 and shared.sigma_ref == (1.0, 0.05, 1.0)
    assert len(measurement_noise(shared, 2)) == 16


def test_first_control_barriers_watch_the_applied_input_at_every_step(problem):
    """Late in the horizon the step's own input is fine, but the first control (the applied one) breaks its
    bounds: only the four first-control barriers read it."""
    far = (np.array([500.0, 500.0]), np.array([2.0, -2.0]), np.array([20.0, 20.0]), np.zeros(2), np.ones(2, bool))
    x = np.array([[10.0, 2.0, 0.0, 20.0]])
    fine, zero = np.zeros((1, 2)), np.zeros(2)
    u0 = np.array([[-9.0, 0.2]])  # beyond a_min and the steering bound, and far from the last input (rates)
    h = measure(problem, x, fine, fine, u0, zero, 2.0, 20.0, 0.0, far)
    k = 5 + 2  # tracking rows, then one barrier per OV
    assert np.all(h[0, k:k + 5] < 1e-3)  # edge, the step's input and rate barriers
    assert np.all(h[0, k + 5:] > 1.0)  # the first control's input and rate barriers


@pytest.mark.parametrize("xp", [np, jnp])
def test_the_reference_lane_changes_at_the_lane_change_rate(scene, xp):
    """From the EV's lateral offset toward the reference lane at ``lane_change_rate``, then held there; ``inf`` is
    the step (every state of the horizon asks for the far lane)."""
    ego = xp.asarray([50.0, 2.0, 0.0, 25.0])  # straight road: the lateral offset is y
    ref = xp.asarray([25.0, 0.0, -2.0])
    _, _, lane, course = reference_profile(make_problem(scene, ProblemConfig(lane_change_rate=1.5)), ref, ego, 40)
    lane = np.asarray(lane)
    np.testing.assert_allclose(lane[:5], 2.0 - 0.15 * np.arange(5), atol=1e-5)
    assert np.all(np.diff(lane) <= 1e-6) and np.all(np.diff(lane) >= -0.15 - 1e-5)
    np.testing.assert_allclose(lane[27:], -2.0, atol=1e-5)  # 4 m at 1.5 m/s: there from t = 2.67 s
    _, _, step, _ = reference_profile(make_problem(scene, ProblemConfig()), ref, ego, 40)
    np.testing.assert_allclose(np.asarray(step)[1:], -2.0, atol=1e-5)
    assert np.all(np.asarray(course) == 0.0)  # the heading term aims along the road unless the scene's lane leads


@pytest.mark.parametrize("xp", [np, jnp])
def test_a_leading_lane_gives_the_heading_of_its_path(scene, xp):
    """Where the scene's reference lane leads through lanes (``Scene.lane_path``), the heading term aims along the
    lane's path while it moves (``arctan(rate / v)``) and along the road once it is there; a plan that holds that
    heading is measured on course, one along the road off it."""
    lead = dataclasses.replace(scene, lane_path=True)
    problem = make_problem(lead, ProblemConfig(lane_change_rate=1.5))
    ego, ref = xp.asarray([50.0, 2.0, 0.0, 25.0]), xp.asarray([25.0, 0.0, -2.0])
    v, _, lane, course = (np.asarray(r) for r in reference_profile(problem, ref, ego, 40))
    np.testing.assert_allclose(course[1:26], np.arctan(-1.5 / 25.0), rtol=1e-5)
    np.testing.assert_allclose(course[28:], 0.0)
    far = tuple(np.full(1, x) for x in (1e3, 0.0, 0.0, 0.0)) + (np.zeros(1, bool),)
    x = np.array([[60.0, 1.0, np.arctan(-1.5 / 25.0), 25.0], [60.0, 1.0, 0.0, 25.0]])
    zero = np.zeros((2, 2))
    h = measure(problem, x, zero, zero, zero, np.zeros(2), 1.0, 25.0, 0.0, far, float(course[5]))
    np.testing.assert_allclose(h[:, 1], [0.0, -np.arctan(-1.5 / 25.0)], atol=1e-6)


@pytest.mark.parametrize("bad", [0.0, -1.0])
def test_a_lane_change_rate_must_be_positive(bad):
    from bimp.configs import ConfigError

    with pytest.raises(ConfigError, match="lane_change_rate"):
        ProblemConfig(lane_change_rate=bad)


# --- every planner: observations and default configs (issue 24) -----------------------------------------------
@pytest.mark.parametrize("name", ["enkts", "enks", "mppi", "nmpc", "lane-keep"])
def test_every_policy_refuses_observations_that_are_not_real_numbers(name):
    """A complex observation was planned on without its imaginary part; bools, numeric strings and objects were
    converted to floats."""
    from bimp.agents import make_policy

    env = gym.make("bimp/EmergencyBrake-v0")
    obs, _ = env.reset(seed=0)
    policy = make_policy(name, env)
    bad = {"complex": obs + 1j, "bool": obs > 0, "<U": obs.astype(str), "object": obs.astype(object)}
    for dtype, value in bad.items():
        with pytest.raises(ValueError, match=f"dtype {dtype}"):
            policy.act(value)
    assert env.action_space.contains(policy.act(obs.astype(np.float64)))  # ints and floats of any width pass


def test_default_resolved_configs_are_unchanged():
    """Committed result records are keyed by the hash of each policy's resolved config: building a policy with no
    config and no overrides must give the same one. These are the hashes of the one config shape (issue 25: every
    planner's own fields plus ``problem``), hashed as issue 28 hashes (fields at their neutral value left out,
    infinities as null, the weights by their sha256); its values are those of commit e3c9e7b's, pinned key by key by
    tests/planners/test_config_shape.py. They changed once since, when the barrier's ``brake_decel`` was renamed
    ``follower_decel`` (values unchanged; ``bimp migrate`` rehashed the committed records)."""
    from bimp.agents import make_policy
    from bimp.agents.evaluation.provenance import config_hash, resolved_config

    env = gym.make("bimp/Overtaking-v0")
    hashes = {name: config_hash(name, resolved_config(make_policy(name, env)))
              for name in ("enkts", "enks", "mppi", "nmpc", "nmpc-t")}
    assert hashes == {"enkts": "19425dcad15426c8", "enks": "93129a5653cd37cf", "mppi": "e6310354491e83f1",
                      "nmpc": "bb113f44a62ed83f", "nmpc-t": "d75f7962508ada94"}


def test_the_steering_scales_follow_the_roads_steering_bound(scene):
    """for_road: the paper's scenarios (the bound the scales were tuned at) keep the config as it is; a road with a
    twelve times wider bound (intersection-v0) has twelve times the steering increments' and the feed-forward's
    noise, in every planner's view of it (the problem's noise, EnKTS's settings)."""
    import dataclasses

    from bimp.planners.enkts import EnKTSConfig
    from bimp.planners.problem import STEER_UNIT, for_road

    config = ProblemConfig()
    assert scene.bounds.steer == STEER_UNIT and for_road(config, STEER_UNIT) is config
    wide = for_road(config, 12 * STEER_UNIT)
    assert wide.sigma_du == pytest.approx((config.sigma_du[0], 12 * config.sigma_du[1]))
    assert wide.sigma_input == pytest.approx((config.sigma_input[0], 12 * config.sigma_input[1]))
    env = gym.make("bimp/intersection-v0")
    env.reset(seed=0)
    junction = env.unwrapped.scene
    assert junction.bounds.steer == pytest.approx(12 * STEER_UNIT)
    noise, base = make_problem(junction, config).noise, make_problem(scene, config).noise
    assert noise[4] == pytest.approx(12 * base[4]) and np.allclose(noise[:4], base[:4])
    assert np.allclose(noise[5:], config.sigma_barrier)
    settings = EnKTSConfig(problem=config).settings(junction.n_obstacles, junction.bounds.steer)
    assert settings.sigma_du == pytest.approx(wide.sigma_du)
    assert EnKTSConfig(problem=config).settings(5, STEER_UNIT).sigma_du == pytest.approx(config.sigma_du)
    assert dataclasses.replace(config) == config  # the stored config itself is never changed


def test_the_heading_row_tracks_the_course_where_asked_and_the_edge_the_body(scene):
    """``track_course``: the heading row reads the body's heading plus the slip of the step's steering,
    ``arctan(tan(delta) / 2)`` (highway-env's bicycle moves along it); without it, the body's heading. The edge row
    reads the body's corners either way. ``for_road`` asks for the course where the road's steering bound is not the
    paper's, and ``road_changes`` names everything it changed there (nothing on the paper's roads)."""
    import dataclasses

    from bimp.planners.problem import STEER_UNIT, for_road, road_changes

    config = ProblemConfig()
    body = make_problem(scene, config)
    course = make_problem(scene, dataclasses.replace(config, track_course=True))
    assert (body.course, course.course) == (0.0, 1.0)
    far = (np.array([500.0]), np.array([2.0]), np.array([20.0]), np.zeros(1), np.ones(1, bool))
    x = np.array([[10.0, 2.9, 0.02, 20.0]])  # near the edge, turned a little left
    u = np.array([[0.0, 0.3]])
    h_body, h_course = (measure(p, x, u, u * 0, u, np.zeros(2), 2.0, 20.0, 0.0, far) for p in (body, course))
    slip = np.arctan(0.5 * np.tan(0.3))
    assert h_course[0, 1] == pytest.approx(h_body[0, 1] + slip) and h_body[0, 1] == pytest.approx(0.02, abs=1e-6)
    np.testing.assert_allclose(np.delete(h_course, 1, axis=1), np.delete(h_body, 1, axis=1))  # edges: the body's
    assert road_changes(config, STEER_UNIT) == {} and for_road(config, STEER_UNIT).track_course is False
    assert road_changes(config, 6 * STEER_UNIT) == {"sigma_du": (0.5, pytest.approx(6 * config.sigma_du[1])),
                                                    "sigma_input": (3.0, pytest.approx(6 * config.sigma_input[1])),
                                                    "track_course": True}
    env = gym.make("bimp/u-turn-v0")  # a curved road: the planners' problem there tracks the course by default
    env.reset(seed=0)
    assert env.unwrapped.scene.bounds.steer == pytest.approx(6 * STEER_UNIT)
    assert make_problem(env.unwrapped.scene, config).course == 1.0 and body.course == 0.0


def _straight_paths(ovs, steps, dt=0.1):
    """Each OV's path ``(K, steps + 1, 3)`` straight along its heading at its constant speed (no acceleration)."""
    t = dt * np.arange(steps + 1)
    direction = np.stack([np.cos(ovs[:, 3]), np.sin(ovs[:, 3])], axis=1)
    xy = ovs[:, None, 1:3] + ovs[:, 4, None, None] * t[None, :, None] * direction[:, None]
    return np.concatenate([xy, np.broadcast_to(ovs[:, None, 3:4], (len(ovs), steps + 1, 1))], axis=2)


def test_paths_along_the_headings_predict_as_the_heading_rule(problem):
    """Given the paths the heading rule would draw (straight, constant speed), the prediction along paths is that
    rule's, in numpy and in JAX; a horizon longer than the paths goes on straight at their last step."""
    ovs = np.array([[1.0, 50.0, 2.0, 0.0, 10.0, 0.0], [1.0, 30.0, -2.0, 0.05, 20.0, 0.0]])
    by_heading = predict_obstacles(problem, ovs, 30)
    along = predict_obstacles(problem._replace(paths=_straight_paths(ovs, 40)), ovs, 30)
    short = predict_obstacles(problem._replace(paths=_straight_paths(ovs, 10)), ovs, 30)
    for a, b, c in zip(by_heading[:4], along[:4], short[:4]):
        np.testing.assert_allclose(b, a, atol=1e-6)
        np.testing.assert_allclose(c, a, atol=1e-6)
    p32 = jax.tree.map(lambda a: jnp.asarray(a, jnp.float32), problem._replace(paths=_straight_paths(ovs, 40)))
    jitted = jax.jit(lambda p, o: predict_obstacles(p, o, 30))(p32, jnp.asarray(ovs, jnp.float32))
    for a, b in zip(by_heading[:4], jitted[:4]):
        np.testing.assert_allclose(np.asarray(b), a, atol=2e-3)


def test_a_path_that_turns_away_is_predicted_along_it(problem):
    """An OV whose path turns off the road's direction is predicted where the path goes, not along its heading."""
    ovs = np.array([[1.0, 50.0, 2.0, 0.0, 10.0, 0.0]])
    paths = _straight_paths(ovs, 20)
    paths[0, :, 1] += np.linspace(0.0, 3.0, 21)  # drifts 3 m to the right over 2 s, heading along the road
    _, lat, v, _, _ = predict_obstacles(problem._replace(paths=paths), ovs, 20)
    np.testing.assert_allclose(lat[:, 0], 2.0 + np.linspace(0.0, 3.0, 21), atol=1e-6)
    np.testing.assert_allclose(v[:, 0], 10.0)


def test_a_leading_lane_drops_the_headway_from_the_keep_out_boxes_and_says_so(scene):
    """On a road whose reference lane leads through the gaps (``Scene.lane_path``) the behaviour layer has picked
    the gap: no time headway in the OVs' boxes (the least gap and braking room stay), recorded as a road change."""
    config = ProblemConfig()
    assert for_road(config, STEER_UNIT) is config and road_changes(config, STEER_UNIT) == {}
    changes = road_changes(config, STEER_UNIT, lane_path=True)
    assert changes == {"barrier": dataclasses.replace(config.barrier, headway=0.0)}
    plain = make_problem(scene, config)
    lead = make_problem(dataclasses.replace(scene, lane_path=True), config)
    assert plain.barrier.headway == config.barrier.headway > 0 and lead.barrier.headway == 0.0
    assert (plain.lane_heading, lead.lane_heading) == (0.0, 1.0)
    assert lead.barrier.follower_decel == plain.barrier.follower_decel
