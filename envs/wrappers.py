"""The planning-features view of a bimp env, for learning agents: :func:`features` as observation, an action on
the *planning* bounds (:func:`to_env_action`). The RL baseline trains through :class:`PlanningWrapper` and acts
through the same functions (:class:`bimp.agents.rl.SB3Policy`).

highway-env's own SB3 examples feed the raw observation and the raw action space to the agent. For continuous
control on these scenarios that fails in known ways, so both sides go through fixed transforms built from the raw
observation and the scene alone:

- Observation: world positions grow to hundreds of metres, and the same situation at another place on the
  road looks new to the network. :func:`features` is ego-relative and scaled to O(1): lateral error to the
  reference lane, heading error to the road, speed error, the previous input, curvature now and ahead, and
  each OV's gap along the road, lateral offset and relative speed (road coordinates). Hand-scaled features
  need no ``VecNormalize`` statistics, which would otherwise have to ship beside the model.
- Action: the env's [-1, 1] spans actuators far wider than the planning bounds (steering +-0.3 rad against
  0.05 rad), so uniform exploration mostly spins the car off the road. The agent's [-1, 1] maps onto the
  *planning* bounds (0 = coast, straight) and the input is then rate-limited around the previous one, so
  every input applied satisfies paper eq. 4-5, like the planners it is compared with.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np

from bimp.envs.checks import checked_action
from bimp.envs.road import wrap_angle
from bimp.envs.scene import Scene

# Feature scales: typical magnitudes, so features are O(1) without running statistics.
_GAP_SCALE = 50.0  # m along the road
_SPEED_SCALE = 10.0  # m/s, speed differences
_V_SCALE = 30.0  # m/s, absolute speeds
_HEADING_SCALE = 0.1  # rad
_CURVATURE_SCALE = 100.0  # 1/m -> 0.5 on a 200 m radius
_ACCEL_SCALE = 7.0  # m/s^2
_LOOKAHEAD_S = 2.0  # s of travel for the curvature ahead
_FEATURE_CLIP = 5.0
LANE_WIDTH = 4.0  # m: highway-env's lane width, the features' lateral unit

N_EGO_FEATURES = 11
N_OV_FEATURES = 5


def n_features(scene: Scene) -> int:
    return N_EGO_FEATURES + scene.n_obstacles * N_OV_FEATURES


def _input_to_unit(u: np.ndarray, scene: Scene) -> np.ndarray:
    """Physical input ``[a, delta]`` -> the agent's units (inverse of the map in :func:`to_physical`)."""
    a_min, a_max = scene.bounds.accel
    a = u[0] / a_max if u[0] >= 0 else u[0] / -a_min
    return np.array([a, u[1] / scene.bounds.steer])


def features(obs: np.ndarray, scene: Scene) -> np.ndarray:
    """Ego-relative, scaled features ``(n_features(scene),)`` float32 of a raw observation ``(scene.obs_dim,)``.

    Ego: lateral error to the reference lane and lateral position (per lane width, per half width), heading
    error to the road (per 0.1 rad), speed error (per 10 m/s), speed and reference speed (per 30 m/s),
    reference acceleration (per 7 m/s^2), previous input in the agent's units, road curvature here and
    ``_LOOKAHEAD_S`` ahead. Per OV: present, gap along the road (per 50 m), lateral offset (per lane width),
    speed along the road relative to the EV and its own acceleration along the road (an oncoming OV's
    negative); zeros when absent. Clipped to +-5.
    """
    ego, prev_u, ovs, ref = scene.split_obs(obs)
    road = scene.road
    # One road-coordinate query for the EV and all OVs: it is the costly part of the features.
    p = road.project(np.concatenate([ego[None, :2], ovs[:, 1:3]]))
    s_e, l_e, s_o, l_o = p.s[0], p.l[0], p.s[1:], p.l[1:]
    half_width = (p.right[0] - p.left[0]) / 2
    v_ref, a_ref, l_ref = ref
    ego_f = [
        (l_e - l_ref) / LANE_WIDTH,
        (l_e - (p.left[0] + half_width)) / half_width,
        wrap_angle(ego[2] - p.heading[0]) / _HEADING_SCALE,
        (ego[3] - v_ref) / _SPEED_SCALE,
        ego[3] / _V_SCALE,
        v_ref / _V_SCALE,
        a_ref / _ACCEL_SCALE,
        *_input_to_unit(prev_u, scene),
        p.curvature[0] * _CURVATURE_SCALE,
        road.curvature_at(s_e + ego[3] * _LOOKAHEAD_S) * _CURVATURE_SCALE,
    ]
    present = ovs[:, 0] > 0
    # Speeds are magnitudes: an OV driving against the road (oncoming, on a two-way road) counts negative, or it
    # would look like traffic at its speed going our way. Exactly 1 for every other OV.
    along = np.where(np.cos(ovs[:, 3] - p.heading[1:]) < 0.0, -1.0, 1.0)
    ov_f = np.stack([
        np.ones_like(s_o),
        (s_o - s_e) / _GAP_SCALE,
        (l_o - l_e) / LANE_WIDTH,
        (along * ovs[:, 4] - ego[3]) / _SPEED_SCALE,
        along * ovs[:, 5] / _ACCEL_SCALE,
    ], axis=-1) * present[:, None]
    out = np.concatenate([np.asarray(ego_f, float), ov_f.ravel()])
    return np.clip(out, -_FEATURE_CLIP, _FEATURE_CLIP).astype(np.float32)


def to_physical(action: np.ndarray, obs: np.ndarray, scene: Scene) -> np.ndarray:
    """The agent's action ``(2,)`` in [-1, 1] -> physical input ``[a m/s^2, delta rad]``.

    Piecewise linear onto the planning bounds with 0 -> coasting straight (the untrained policy's mean then
    neither brakes nor accelerates), then clipped to the rate bounds around the previous input read from
    ``obs``, so the output satisfies paper eq. 4-5.
    """
    x = np.clip(np.asarray(action, float).reshape(2), -1.0, 1.0)
    b = scene.bounds
    u = np.array([x[0] * (b.accel[1] if x[0] >= 0 else -b.accel[0]), x[1] * b.steer])
    prev = scene.split_obs(obs)[1]
    rate = np.array([b.accel_rate, b.steer_rate])
    return np.clip(u, prev - rate, prev + rate)


def to_env_action(action: np.ndarray, obs: np.ndarray, scene: Scene) -> np.ndarray:
    """The agent's action -> the env's normalized action ``(2,)`` float32 in [-1, 1]."""
    return scene.to_normalized(to_physical(action, obs, scene)).astype(np.float32)


class PlanningWrapper(gym.Wrapper):
    """Training-side view of a bimp env: :func:`features` as observation, the agent's planning-bound action
    in [-1, 1]^2 (:func:`to_env_action`). Reward, termination and ``info`` pass through unchanged."""

    def __init__(self, env: gym.Env):
        super().__init__(env)
        n = n_features(env.unwrapped.scene)
        self.observation_space = gym.spaces.Box(-_FEATURE_CLIP, _FEATURE_CLIP, shape=(n,), dtype=np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        self._raw: np.ndarray | None = None

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self._raw = obs
        return features(obs, self.env.unwrapped.scene), info

    def step(self, action):
        # The scene is rebuilt at every reset: read it at each step, never cache it.
        scene = self.env.unwrapped.scene
        # Checked before the map: it would turn a bool or a numeric string into floats the env then accepts.
        action = checked_action(action)
        obs, reward, terminated, truncated, info = self.env.step(to_env_action(action, self._raw, scene))
        self._raw = obs
        return features(obs, scene), reward, terminated, truncated, info


__all__ = ["PlanningWrapper", "features", "n_features", "to_env_action", "to_physical"]
