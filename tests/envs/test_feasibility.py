"""Feasible instances by construction: for every instance of a scenario's documented parameter ranges a plan inside
the planning bounds exists. An oracle simulates the longitudinal motion in the EV's lane exactly as highway-env steps
it (position with the step's starting speed, then speed, clamped at 0) and checks the plan that brakes at the bounds
(a_min, and at most ``accel_rate`` more per step: :func:`bimp.envs.oracle.brake_at_the_bounds`, shared with the
suite's families); the oracle is first checked against the env itself."""

from __future__ import annotations

import itertools

import gymnasium as gym
import numpy as np
import pytest

from bimp import envs  # noqa: F401  (registers the envs)
from bimp.envs.oracle import brake_at_the_bounds
from bimp.envs.scenarios import OvertakingEnv
from bimp.envs.scene import Bounds

DRAWS = 1000
B = Bounds()


def pass_margin(ev, gap1, v1, gap2, v2, held=3.0, headway=0.6, dt=0.1, duration=15.0, length=5.0):
    """How far [m] ahead of OV1 (centre to centre) the EV ends an overtaking episode in the worst case of a pass
    ``(...)``: held behind OV1 at its speed, ``headway`` s plus a car and ``d_min`` behind it, until ``held`` s,
    then in the left lane accelerating at ``a_max`` toward the behaviour layer's speed (the cruise speed, OV2's
    once OV2 is within ``consider_s`` of travel). The OVs hold speed and lane. Arrays broadcast."""
    ev, gap1, v1, gap2, v2 = np.broadcast_arrays(*(np.asarray(a, float) for a in (ev, gap1, v1, gap2, v2)))
    s_1, s_2, v = gap1 + v1 * held, gap2 + v2 * held, v1.copy()
    s_e = s_1 - (length + B.d_min + headway * v1)
    for _ in range(round((duration - held) / dt)):
        close = s_2 - s_e < OvertakingEnv.BEHAVIOUR.consider_s * np.maximum(v, 1.0)
        a = np.clip((np.where(close, np.minimum(v2, ev), ev) - v) / dt, *B.accel)
        s_e, v = s_e + v * dt, v + a * dt
        s_1, s_2 = s_1 + v1 * dt, s_2 + v2 * dt
    return s_e - s_1


def drawn(env_id: str, n: int = DRAWS) -> list[dict]:
    env = gym.make(env_id)
    params = []
    for seed in range(n):
        env.reset(seed=seed)
        params.append(dict(env.unwrapped.drawn_params))
    return params


def corners(env_id: str, keys: tuple[str, ...]) -> list[dict]:
    ranges = {k: gym.make(env_id).unwrapped.config[k] for k in keys}
    values = [r if np.ndim(r) else [r] for r in ranges.values()]
    return [dict(zip(keys, c)) for c in itertools.product(*values)]


class RampBrake:
    """Lane keeping until the OVs' deceleration shows, then braking at the planning bounds (rate-limited)."""

    def __init__(self, env):
        from bimp.agents.baselines import LaneKeeping

        self.keep, self.env, self.braking, self.a = LaneKeeping(env), env, False, 0.0

    def act(self, obs):
        scene = self.env.unwrapped.scene
        action = self.keep.act(obs)
        self.braking |= scene.split_obs(obs)[2][:, 5].min() < -1.0  # the deceleration this observation shows
        if self.braking:
            self.a = max(self.a - B.accel_rate, B.accel[0])
            action[0] = scene.to_normalized([self.a, 0.0])[0]
        else:
            action[0] = scene.to_normalized([0.0, 0.0])[0]
        return action


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_oracle_is_the_env(seed):
    """Driven by the braking plan, the env's least gap to OV1 is the oracle's, to float rounding."""
    env = gym.make("bimp/EmergencyBrake-v0", config={"ov2_gap": 300.0})
    obs, _ = env.reset(seed=seed)
    p = env.unwrapped.drawn_params
    policy, least, done = RampBrake(env), np.inf, False
    while not done:
        obs, _, term, trunc, info = env.step(policy.act(obs))
        least, done = min(least, info["ov_distance"][0]), term or trunc
    expected = brake_at_the_bounds(p["ev_speed"], p["ov1_gap"], p["ov_speed"][0], p["brake_onset"], p["brake_decel"])
    assert least == pytest.approx(float(expected), abs=0.05)


def test_emergency_brake_braking_at_the_bounds_stops_clear_on_every_draw_and_corner():
    """From the first observed deceleration, braking at the bounds keeps at least d_min to OV1: on 1000 draws of
    the documented ranges and on every corner of them (the worst case: fastest EV, nearest and slowest OV braking
    hardest and latest)."""
    params = drawn("bimp/EmergencyBrake-v0")
    gaps = brake_at_the_bounds(*(np.array([p[k] if k != "ov_speed" else p[k][0] for p in params])
                                 for k in ("ev_speed", "ov1_gap", "ov_speed", "brake_onset", "brake_decel")))
    assert gaps.min() >= B.d_min, f"{int(np.sum(gaps < B.d_min))} draws infeasible, e.g. {params[int(gaps.argmin())]}"
    keys = ("ev_speed", "ov1_gap", "ov_speed", "brake_onset", "brake_decel")
    worst = min(float(brake_at_the_bounds(*(c[k] for k in keys))) for c in corners("bimp/EmergencyBrake-v0", keys))
    assert worst >= B.d_min


def test_the_old_emergency_brake_range_was_not_feasible():
    """Why the range changed: with OV1 40 m ahead the worst instance collides even braking at the bounds."""
    assert brake_at_the_bounds(27.0, 40.0, 20.0, 1.2, 7.0) < 0


def test_overtaking_following_ov1_is_always_safe():
    """OV1 holds its speed; braking at the bounds from the start keeps at least d_min behind it: 1000 draws, every
    corner."""
    params = drawn("bimp/Overtaking-v0")
    never = 1e9  # OV1 never brakes in this scenario
    gaps = brake_at_the_bounds(*(np.array([p[k] for p in params]) for k in ("ev_speed", "ov1_gap", "ov1_speed")),
                               onset=never, decel=0.0, react=False)
    assert gaps.min() >= B.d_min
    keys = ("ev_speed", "ov1_gap", "ov1_speed")
    worst = min(float(brake_at_the_bounds(*(c[k] for k in keys), onset=never, decel=0.0, react=False))
                for c in corners("bimp/Overtaking-v0", keys))
    assert worst >= B.d_min


def test_overtaking_a_pass_exists_on_every_draw_and_corner():
    """Even held behind OV1 for 3 s, the EV can end the episode ahead of OV1 (by more than a car) on 1000 draws
    and every corner: OV2, ahead in the passing lane, outpaces OV1 by the ranges' order."""
    keys = ("ev_speed", "ov1_gap", "ov1_speed", "ov2_gap", "ov2_speed")
    params = drawn("bimp/Overtaking-v0")
    margins = pass_margin(*(np.array([p[k] for p in params]) for k in keys))
    assert margins.min() > 5.0, f"no pass on {params[int(margins.argmin())]}"
    assert min(float(pass_margin(*(c[k] for k in keys))) for c in corners("bimp/Overtaking-v0", keys)) > 5.0


def test_the_old_overtaking_ranges_had_no_pass():
    """Why OV2 must outpace OV1: with OV2 slower (the old ranges allowed 17 vs 18 m/s) the held EV ends behind."""
    assert pass_margin(27.0, 35.0, 18.0, 100.0, 17.0) < 0
