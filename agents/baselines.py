"""Simple reference controllers: floors every planner must beat (lane keeping blind to the OVs, doing nothing)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np

from bimp.configs import ConfigError, check_fields, load_config
from bimp.envs.road import wrap_angle


@dataclass(frozen=True)
class LaneKeepingConfig:
    """Gains of :class:`LaneKeeping`, each >= 0 and finite (0 switches its term off): k_lat [rad/m] steering per
    metre of lateral error to the reference lane, k_head [rad/rad] per radian of heading error, k_speed [1/s]
    acceleration per m/s of speed error. A bad value raises :class:`bimp.configs.ConfigError` naming the key and
    the value."""

    k_lat: float = 0.004
    k_head: float = 0.15
    k_speed: float = 0.8

    def __post_init__(self) -> None:
        check_fields(self)
        for key in ("k_lat", "k_head", "k_speed"):
            if getattr(self, key) < 0:
                raise ConfigError(key, "a finite number >= 0", getattr(self, key))


def search_space() -> dict:
    """The gains ``bimp tune`` searches for lane keeping (log-uniform over a decade or more around the
    defaults)."""
    from optuna.distributions import FloatDistribution as Float

    return {"k_lat": Float(0.001, 0.02, log=True), "k_head": Float(0.02, 0.5, log=True),
            "k_speed": Float(0.1, 2.0, log=True)}


class LaneKeeping:
    """Proportional lane keeping at the reference speed, blind to the OVs.

    Steering: curvature feedforward plus feedback on the lateral and heading errors to the reference lane;
    acceleration: proportional to the speed error. Both clipped to the planning bounds. Configured as the
    planners are: :class:`LaneKeepingConfig`'s defaults, the YAML ``config`` (a file of overrides) if given, then
    ``overrides`` (``k_lat=0.01``); an unknown key or a bad value raises naming it.
    """

    def __init__(self, env: gym.Env, config: str | Path | None = None, **overrides):
        self.env = env
        self.config = load_config(LaneKeepingConfig, config, **overrides)
        self.step_info: dict = {}  # a fixed control law: nothing to say about a step

    def reset(self, seed: int | None = None) -> None:
        """Deterministic: nothing to seed."""

    def act(self, obs: np.ndarray) -> np.ndarray:
        scene, gains = self.env.unwrapped.scene, self.config
        ego, _, _, ref = scene.split_obs(scene.check_obs(obs))
        here = scene.road.project(ego[:2])
        lat, heading_err = here.l, wrap_angle(ego[2] - here.heading)
        feedforward = np.arctan(scene.vehicle_length * here.curvature)
        steer = feedforward - gains.k_lat * (lat - ref[2]) - gains.k_head * heading_err
        accel = gains.k_speed * (ref[0] - ego[3])
        b = scene.bounds
        u = np.array([np.clip(accel, *b.accel), np.clip(steer, -b.steer, b.steer)])
        return scene.to_normalized(u).astype(np.float32)


class ZeroAction:
    """The do-nothing reference: action [0, 0] in the env's space (coast straight on, actuators centred)."""

    def __init__(self, env: gym.Env):
        self.action = np.zeros(env.action_space.shape, dtype=np.float32)
        self.config: dict = {}
        self.step_info: dict = {}

    def act(self, obs: np.ndarray) -> np.ndarray:
        return self.action

    def reset(self, seed: int | None = None) -> None:
        """Deterministic: nothing to seed."""
