"""The ``paper-noisy`` family (issue 27): the paper's two scenarios with observation noise and an EV whose dynamics are
off its model's. Every instance keeps the oracle's safe plan under the mismatch (1000 draws per difficulty, every
corner, the env driven by the plan); the noise reaches the observation only; the mismatch changes the EV's response
by the documented amount; refusals name the key; seeded resets are deterministic; the planners drive it."""

from __future__ import annotations

import itertools

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import bimp
from bimp import make_policy
from bimp.envs.oracle import NEVER, braking
from bimp.envs.scenarios import EgoVehicle, OvertakingEnv
from bimp.envs.scene import DT, VEHICLE_LENGTH, Bounds
from bimp.envs.suite.paper_noisy import (
    FAMILY,
    STEER_HEADROOM,
    STRAIGHT_IN,
    MismatchedEgoVehicle,
    NoisyEmergencyBrakeEnv,
    NoisyOvertakingEnv,
    lag_gain,
    steer_to_hold,
)
from tests.envs.test_suite_families import drawn_params

pytestmark = pytest.mark.filterwarnings("ignore")
OT, EB = "bimp/overtaking-noisy-v0", "bimp/emergency-brake-noisy-v0"
DRAWS = 1000
B = Bounds()
EXACT = {"ov_position_noise": 0.0, "ov_speed_noise": 0.0, "length_ratio": 1.0, "accel_lag": 0.0, "grip": 1.0}
DIFFICULTIES = ("easy", "medium", "hard")
EB_KEYS = ("ev_speed", "ov1_gap", "ov_speed", "brake_onset", "brake_decel", "accel_lag", "grip")
OT_KEYS = ("ev_speed", "ov1_gap", "ov1_speed", "accel_lag", "grip")


def scenario_id(cls, difficulty: str) -> str:
    return f"bimp/{cls.NAME}{'' if difficulty == cls.DEFAULT_DIFFICULTY else '-' + difficulty}-v0"


def real_draws(cls, difficulty: str, keys: tuple[str, ...], n: int = DRAWS) -> dict[str, np.ndarray]:
    """``keys`` of the registered env's ``drawn_params`` at ``difficulty`` over ``reset(seed=i)``, i < ``n``: the
    env's own draws, in its order (1000 resets take a few seconds); a key drawn once per OV (``ov_speed``) gives
    OV1's, the first drawn."""
    rows = drawn_params(scenario_id(cls, difficulty), n=n)
    return {k: np.array([r[k][0] if isinstance(r[k], list) else r[k] for r in rows]) for k in keys}


def pass_margin_with_lag(ev, gap1, v1, gap2, v2, lag, held=3.0, headway=0.6, dt=DT, duration=15.0):
    """``tests/envs/test_feasibility.pass_margin`` (the EV held behind OV1 for ``held`` s, then accelerating at the
    bounds in the left lane toward the behaviour layer's speed) with the achieved acceleration lagging the command by
    ``lag`` [s]: how far [m] ahead of OV1 the EV ends the episode. Arrays broadcast."""
    ev, gap1, v1, gap2, v2, lag = np.broadcast_arrays(*(np.asarray(a, float) for a in (ev, gap1, v1, gap2, v2, lag)))
    alpha = lag_gain(lag, dt)
    s_1, s_2, v, a = gap1 + v1 * held, gap2 + v2 * held, v1.copy(), np.zeros(ev.shape)
    s_e = s_1 - (VEHICLE_LENGTH + B.d_min + headway * v1)
    for _ in range(round((duration - held) / dt)):
        close = s_2 - s_e < OvertakingEnv.BEHAVIOUR.consider_s * np.maximum(v, 1.0)
        a = a + alpha * (np.clip((np.where(close, np.minimum(v2, ev), ev) - v) / dt, *B.accel) - a)
        s_e, v = s_e + v * dt, v + a * dt
        s_1, s_2 = s_1 + v1 * dt, s_2 + v2 * dt
    return s_e - s_1


def corners(env, keys: tuple[str, ...]) -> list[dict]:
    values = [env.config[k] if isinstance(env.config[k], tuple) else (env.config[k],) for k in keys]
    return [dict(zip(keys, c)) for c in itertools.product(*values)]


# --- the oracle -------------------------------------------------------------------------------------------------
def lagged(ev, gap, v_ov, onset, decel, lag, grip=1.0, **kwargs):
    """:func:`bimp.envs.oracle.braking` with the lag and the grip in the order of the draws (``EB_KEYS``)."""
    return braking(ev, gap, v_ov, onset, decel, lag=lag, grip=grip, **kwargs)


def test_the_lag_and_the_grip_only_shorten_the_oracles_braking():
    """The shared oracle's lag and grip: a longer lag or less grip leaves less gap and a longer way to the stop; a
    vanishing lag is no lag (the command achieved at once)."""
    rng = np.random.default_rng(0)
    args = (rng.uniform(20, 30, 50), rng.uniform(40, 80, 50), rng.uniform(15, 25, 50), rng.uniform(0.5, 1.5, 50),
            rng.uniform(4, 8, 50))
    np.testing.assert_allclose(braking(*args, lag=1e-9)[0], braking(*args, lag=0.0)[0], atol=1e-9)  # lag -> 0
    for less, more in [(braking(*args, lag=0.4), braking(*args, lag=0.2)),
                       (braking(*args, lag=0.4, grip=0.8), braking(*args, lag=0.4))]:
        assert np.all(less[0] <= more[0]) and np.mean(less[0] < more[0]) > 0.9  # equal where the least is at once
        assert np.all(less[1] >= more[1])  # and a longer way to the stop


@pytest.mark.parametrize("difficulty", DIFFICULTIES)
def test_emergency_brake_stops_clear_under_the_mismatch_on_every_draw_and_corner(difficulty):
    """Braking at the bounds once OV1's deceleration shows, through the EV's lag and grip, keeps at least d_min to
    OV1: on 1000 draws of each difficulty and every corner of its ranges."""
    d = real_draws(NoisyEmergencyBrakeEnv, difficulty, EB_KEYS)
    gaps, _ = lagged(*(d[k] for k in EB_KEYS))
    assert gaps.min() >= B.d_min, f"{int(np.sum(gaps < B.d_min))} draws infeasible"
    env = gym.make(scenario_id(NoisyEmergencyBrakeEnv, difficulty)).unwrapped
    rows = corners(env, EB_KEYS)
    worst = lagged(*(np.array([c[k] for c in rows]) for k in EB_KEYS))[0]
    assert worst.min() >= B.d_min
    for key in ("accel_lag", "grip"):
        lo, hi = env.config[key]
        assert all(lo <= v <= hi for v in d[key])


@pytest.mark.parametrize("difficulty", DIFFICULTIES)
def test_overtaking_following_ov1_stays_safe_on_the_straight_under_the_mismatch(difficulty):
    """Braking at the bounds from the first step keeps at least d_min behind OV1 and stops on the straight before
    the curve (so the wheelbase never has to steer it); a pass still exists; the curve's hold at the longest EV is
    inside the steering bound: 1000 draws and every corner."""
    env = gym.make(scenario_id(NoisyOvertakingEnv, difficulty)).unwrapped
    keys = (*OT_KEYS, "ov2_gap", "ov2_speed")
    d = real_draws(NoisyOvertakingEnv, difficulty, keys)
    for sample in (d, {k: np.array([c[k] for c in corners(env, keys)]) for k in keys}):
        gaps, travel = lagged(sample["ev_speed"], sample["ov1_gap"], sample["ov1_speed"], NEVER, 0.0,
                                      sample["accel_lag"], sample["grip"], react=False)
        assert gaps.min() >= B.d_min
        assert travel.max() + VEHICLE_LENGTH / 2 <= STRAIGHT_IN
        margins = pass_margin_with_lag(*(sample[k] for k in ("ev_speed", "ov1_gap", "ov1_speed", "ov2_gap",
                                                              "ov2_speed", "accel_lag")))
        assert margins.min() > VEHICLE_LENGTH
    hold = steer_to_hold(min(env.config["radius"]) - 2.0, max(env.config["length_ratio"]) * VEHICLE_LENGTH)
    assert hold <= B.steer - STEER_HEADROOM


@pytest.mark.parametrize("cls", FAMILY)
def test_real_resets_draw_inside_the_ranges_and_keep_the_oracle(cls):
    """The env's own resets (20 seeds of hard) draw every range inside its preset, and the oracle holds on them."""
    env = gym.make(scenario_id(cls, "hard")).unwrapped
    for seed in range(20):
        env.reset(seed=seed)
        p = env.drawn_params
        for key, (lo, hi) in cls.DIFFICULTIES["hard"].items():
            assert lo <= p[key] <= hi, (key, p)
        if cls is NoisyEmergencyBrakeEnv:
            gap = lagged(p["ev_speed"], p["ov1_gap"], p["ov_speed"][0], p["brake_onset"], p["brake_decel"],
                                 p["accel_lag"], p["grip"])[0]
        else:
            gap = lagged(p["ev_speed"], p["ov1_gap"], p["ov1_speed"], NEVER, 0.0, p["accel_lag"], p["grip"],
                                 react=False)[0]
        assert gap >= B.d_min


class TruthBrake:
    """The oracle's plan in the env, blind to the observation: straight (steering 0), the command ramped to a_min by
    the rate bound from the step after OV1's true deceleration shows (emergency brake) or from the first step."""

    def __init__(self, env, react: bool):
        self.env, self.react, self.a, self.braking = env.unwrapped, react, 0.0, not react

    def act(self, obs):
        self.braking |= self.env.obstacles[0].acceleration < -1.0
        if self.braking:
            self.a = max(self.a - B.accel_rate, B.accel[0])
        return self.env.scene.to_normalized(np.array([self.a, 0.0])).astype(np.float32)


def drive(env_id: str, seed: int, react: bool, config: dict | None = None) -> tuple[float, dict, dict]:
    env = gym.make(env_id, config=config)
    obs, _ = env.reset(seed=seed)
    policy, least, done, info = TruthBrake(env, react), np.inf, False, {}
    while not done:
        obs, _, term, trunc, info = env.step(policy.act(obs))
        least, done = min(least, info["ov_distance"][0]), term or trunc
    return least, dict(env.unwrapped.drawn_params), info


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_oracle_is_the_env(seed):
    """Driven by the plan on hard instances, the env's least gap to OV1 is the oracle's under the drawn lag and grip
    (the EV steps as :func:`bimp.envs.oracle.braking` simulates it), with no collision and on the road."""
    least, p, info = drive("bimp/emergency-brake-noisy-hard-v0", seed, react=True, config={"ov2_gap": 300.0})
    expected = lagged(p["ev_speed"], p["ov1_gap"], p["ov_speed"][0], p["brake_onset"], p["brake_decel"],
                              p["accel_lag"], p["grip"])[0]
    assert least == pytest.approx(float(expected), abs=1e-5)
    assert not info["collision"] and not info["offroad"]
    least, p, info = drive("bimp/overtaking-noisy-hard-v0", seed, react=False)
    expected = lagged(p["ev_speed"], p["ov1_gap"], p["ov1_speed"], NEVER, 0.0, p["accel_lag"], p["grip"],
                              react=False)[0]
    assert least == pytest.approx(float(expected), abs=1e-5)
    assert not info["collision"] and not info["offroad"]


@pytest.mark.slow
@pytest.mark.parametrize("difficulty", DIFFICULTIES)
@pytest.mark.parametrize("cls", FAMILY)
def test_the_oracles_plan_is_safe_on_seeds_0_to_99(cls, difficulty):
    """The plan driven through the env on seeds 0-99 of each difficulty: no collision, on the road, at least d_min."""
    for seed in range(100):
        least, p, info = drive(scenario_id(cls, difficulty), seed, react=cls is NoisyEmergencyBrakeEnv)
        assert least >= B.d_min and not info["collision"] and not info["offroad"], (seed, p)


# --- configuration ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("cls", FAMILY)
def test_every_difficulty_is_a_scenario_of_its_own(cls):
    for difficulty, preset in cls.DIFFICULTIES.items():
        name = cls.NAME if difficulty == cls.DEFAULT_DIFFICULTY else f"{cls.NAME}-{difficulty}"
        spec = bimp.envs.scenario_spec(name)
        assert spec.id == scenario_id(cls, difficulty) and spec.max_episode_steps == round(cls.DURATION * 10)
        config = gym.make(spec.id).unwrapped.config
        assert config["difficulty"] == difficulty
        assert {k: config[k] for k in cls.range_keys()} == dict(preset)
    config = gym.make(scenario_id(cls, "hard"), config={"accel_lag": 0.3}).unwrapped.config
    assert config["difficulty"] == "hard" and config["accel_lag"] == 0.3 and config["length_ratio"] == (1.25, 1.5)
    with pytest.raises(ValueError, match="difficulty must be 'hard', the difficulty this id names"):
        gym.make(scenario_id(cls, "hard"), config={"difficulty": "easy"})
    hard = gym.make(scenario_id(cls, "hard"))
    with pytest.raises(ValueError, match="difficulty must be 'hard'"):  # nor for one episode
        hard.reset(seed=0, options={"config": {"difficulty": "easy"}})
    # a difficulty for one episode only, then back on gym.make's
    env = gym.make(f"bimp/{cls.NAME}-v0")
    env.reset(seed=0, options={"config": {"difficulty": "hard"}})
    assert env.unwrapped.config["length_ratio"] == (1.25, 1.5)
    env.reset(seed=0)
    assert env.unwrapped.config["length_ratio"] == cls.DIFFICULTIES["medium"]["length_ratio"]


@pytest.mark.parametrize(("env_id", "config", "key"), [
    (EB, {"difficulty": "extreme"}, "difficulty"),
    (EB, {"ov1_gap": (60.0, 70.0), "accel_lag": (0.3, 0.6), "grip": 1.0}, "accel_lag"),  # 27 m/s, 60 m, 0.6 s: -1.5 m
    (EB, {"grip": (0.7, 0.9)}, "grip"),  # medium's lag (0.25 s) and a grip of 0.7 at 72 m: -2.9 m
    (EB, {"grip": 1.1}, "grip"),  # outside the envelope
    (EB, {"accel_lag": 1.5}, "accel_lag"),  # outside the envelope
    (EB, {"ov1_gap": (45.0, 55.0), "accel_lag": 0.0, "grip": 1.0}, "ov1_gap"),  # 50 m at least for the model's EV
    (EB, {"ov_position_noise": -0.1}, "ov_position_noise"),
    (EB, {"ov_speed_noise": (0.5, 3.0)}, "ov_speed_noise"),
    (EB, {"ov_speed_noise": "high"}, "ov_speed_noise"),
    (EB, {"ev_speed_noise": 0.1}, "ev_speed_noise"),  # unknown: the EV's own state is observed as it is
    (EB, {"length_ratio": (0.5, 1.0)}, "length_ratio"),
    (OT, {"accel_lag": (0.3, 0.6)}, "accel_lag"),  # behind OV1 at 0.6 s: 0.23 m
    (OT, {"length_ratio": 1.5, "radius": 120.0}, "length_ratio"),  # the hold would take 0.064 rad
    (OT, {"ev_speed": 36.0, "ov1_gap": (80.0, 90.0), "accel_lag": 0.0}, "ev_speed"),  # stops past the straight
    (OT, {"grip": 0.8}, "grip"),  # behind OV1 with medium's lag (0.25 s): 0.78 m
    (OT, {"noise": 0.1}, "noise"),  # unknown key
])
def test_refusals_name_the_key(env_id, config, key):
    with pytest.raises(ValueError, match=key):
        gym.make(env_id, config=config)
    env = gym.make(env_id)
    with pytest.raises(ValueError, match=key):  # and for one episode
        env.reset(seed=0, options={"config": config})


def test_check_env_and_determinism():
    for env_id in (OT, EB, "bimp/overtaking-noisy-hard-v0"):
        check_env(gym.make(env_id).unwrapped, skip_render_check=True)
        runs = []
        for seed in (3, 3, 4):
            env = gym.make(env_id)
            obs, _ = env.reset(seed=seed)
            seq = [obs]
            for k in range(10):
                obs, *_ = env.step(np.array([0.05, 0.01 * np.sin(k)], np.float32))
                seq.append(obs)
            runs.append((np.array(seq), dict(env.unwrapped.drawn_params)))
        np.testing.assert_array_equal(runs[0][0], runs[1][0])
        assert runs[0][1] == runs[1][1]
        assert runs[0][1] != runs[2][1] and not np.array_equal(runs[0][0], runs[2][0])


# --- noise and mismatch ---------------------------------------------------------------------------------------
@pytest.mark.parametrize(("noisy", "paper", "config"), [
    (EB, "bimp/EmergencyBrake-v0", {"ov1_gap": (50.0, 60.0)}),
    (OT, "bimp/Overtaking-v0", {}),
])
def test_without_noise_or_mismatch_it_is_the_paper_scenario(noisy, paper, config):
    """The paper env's draws come first and in its order: with no noise and no mismatch the episode is the paper's."""
    envs = [gym.make(noisy, config={**EXACT, **config}), gym.make(paper)]
    seqs = []
    for env in envs:
        obs, _ = env.reset(seed=5)
        seq = [obs]
        for k in range(30):
            obs, _, term, _, info = env.step(np.array([-0.3 * (k > 5), 0.005 * np.sin(k / 3)], np.float32))
            seq.append(obs)
            if term:
                break
        seqs.append((np.array(seq), info["ov_distance"]))
    np.testing.assert_array_equal(seqs[0][0], seqs[1][0])
    assert seqs[0][1] == seqs[1][1]


def test_noise_is_on_the_observation_not_on_the_safety_info():
    """The observation's OV positions and speeds are the true ones plus Gaussian noise of the configured std; the
    EV's own state is observed as it is; the env's info (gaps) is computed on the true state."""
    std = {"ov_position_noise": 0.5, "ov_speed_noise": 0.8}
    env = gym.make(OT, config={**EXACT, **std, "difficulty": "hard"})
    obs, _ = env.reset(seed=0)
    base = env.unwrapped
    errors = {"x": [], "y": [], "speed": []}
    for _ in range(100):
        obs, _, term, trunc, info = env.step(np.array([0.0, 0.0], np.float32))
        ego, _, ovs, _ = base.scene.split_obs(obs)
        true = base._ov_rows()
        errors["x"] += list(ovs[:, 1] - true[:, 1])
        errors["y"] += list(ovs[:, 2] - true[:, 2])
        errors["speed"] += list(ovs[:, 4] - true[:, 4])
        np.testing.assert_array_equal(ego, base._ev_state().astype(np.float32))
        np.testing.assert_array_equal(ovs[:, [0, 3, 5]], true[:, [0, 3, 5]].astype(np.float32))
        assert info["ov_distance"] == base.scene.ov_gaps(base._ev_state(), true).tolist()
        if term or trunc:
            break
    for key, sd in (("x", 0.5), ("y", 0.5), ("speed", 0.8)):
        e = np.array(errors[key])
        assert abs(e.mean()) < 4 * sd / np.sqrt(len(e)) + 1e-3 and np.std(e) == pytest.approx(sd, rel=0.2), key


def test_a_longer_wheelbase_scales_the_yaw_rate():
    """A step of steering turns the EV 1 / length_ratio as fast as the 5 m bicycle its model is: highway-env's yaw
    rate v sin(beta) / (L / 2) with L = length_ratio x 5 m; the position update is the bicycle's."""
    env = gym.make(EB, config={**EXACT, "length_ratio": 1.4})
    env.reset(seed=0)
    base = env.unwrapped
    ev = base.vehicle
    h0, v0 = ev.heading, ev.speed
    env.step(base.scene.to_normalized(np.array([0.0, 0.04])).astype(np.float32))
    delta = ev.action["steering"]  # 0.04 rad, as the float32 action carries it
    assert delta == pytest.approx(0.04, rel=1e-6)
    beta = np.arctan(0.5 * np.tan(delta))
    assert ev.heading - h0 == pytest.approx(v0 * np.sin(beta) / (1.4 * VEHICLE_LENGTH / 2) * DT, rel=1e-9)
    twin = EgoVehicle(base.road, np.zeros(2), h0, v0)  # the model's bicycle, stepped on the same input
    twin.act({"acceleration": 0.0, "steering": delta})
    twin.step(DT)
    assert (ev.heading - h0) / (twin.heading - h0) == pytest.approx(1 / 1.4, rel=1e-9)


def test_the_lag_and_grip_give_a_scaled_first_order_response():
    """A step of the acceleration command reaches grip x a_cmd (1 - exp(-t / lag)) after t; the speed follows the
    achieved acceleration; the drawn footprint and the command in the observation are the command's."""
    lag, grip, a_cmd = 0.3, 0.8, -5.0
    env = gym.make(EB, config={**EXACT, "accel_lag": lag, "grip": grip})
    env.reset(seed=0)
    base = env.unwrapped
    ev = base.vehicle
    assert isinstance(ev, MismatchedEgoVehicle) and ev.LENGTH == VEHICLE_LENGTH
    for n in range(1, 11):
        v0 = ev.speed
        obs, *_ = env.step(base.scene.to_normalized(np.array([a_cmd, 0.0])).astype(np.float32))
        assert ev.applied_acceleration == pytest.approx(grip * a_cmd * (1 - np.exp(-n * DT / lag)), rel=1e-9)
        assert (ev.speed - v0) / DT == pytest.approx(ev.applied_acceleration, rel=1e-9)
        assert base.scene.split_obs(obs)[1][0] == pytest.approx(a_cmd, rel=1e-6)


# --- the planners ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("env_id", ["bimp/overtaking-noisy-hard-v0", "bimp/emergency-brake-noisy-hard-v0"])
def test_short_enkts_episode(env_id):
    env = gym.make(env_id)
    agent = make_policy("enkts", env)
    obs, _ = env.reset(seed=1)
    agent.reset(1)
    for _ in range(10):
        action = agent.act(obs)
        assert action.shape == (2,) and np.all(np.isfinite(action)) and np.all(np.abs(action) <= 1.0)
        obs, _, terminated, truncated, info = env.step(action)
        assert np.all(np.isfinite(obs)) and not info["collision"] and not info["offroad"]
        if terminated or truncated:
            break
