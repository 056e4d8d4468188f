"""Simple reference controllers: floors every planner must beat (lane keeping blind to the OVs, doing nothing)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np


class LaneKeeping:
    """Proportional lane keeping at the reference speed, blind to the OVs.

    Steering: curvature feedforward plus feedback on the lateral and heading errors to the reference lane;
    acceleration: proportional to the speed error. Both clipped to the planning bounds.
    """

    def __init__(self, env: gym.Env, k_lat: float = 0.004, k_head: float = 0.15, k_speed: float = 0.8):
        self.env, self.k_lat, self.k_head, self.k_speed = env, k_lat, k_head, k_speed
        self.config = {"k_lat": k_lat, "k_head": k_head, "k_speed": k_speed}

    @staticmethod
    def search_space() -> dict:
        """The gains ``bimp tune`` searches (log-uniform over a decade or more around the defaults)."""
        from optuna.distributions import FloatDistribution as Float

        return {"k_lat": Float(0.001, 0.02, log=True), "k_head": Float(0.02, 0.5, log=True),
                "k_speed": Float(0.1, 2.0, log=True)}

    def reset(self, seed: int | None = None) -> None:
        """Deterministic: nothing to seed."""

    def act(self, obs: np.ndarray) -> np.ndarray:
        scene = self.env.unwrapped.scene
        ego, _, _, ref = scene.split_obs(scene.check_obs(obs))
        s, lat = scene.road.to_frenet(ego[:2])
        heading_err = ego[2] - scene.road.heading_at(s)
        feedforward = np.arctan(scene.vehicle_length * scene.road.curvature_at(s))
        steer = feedforward - self.k_lat * (lat - ref[2]) - self.k_head * heading_err
        accel = self.k_speed * (ref[0] - ego[3])
        b = scene.bounds
        u = np.array([np.clip(accel, *b.accel), np.clip(steer, -b.steer, b.steer)])
        return scene.to_normalized(u).astype(np.float32)


class ZeroAction:
    """The do-nothing reference: action [0, 0] in the env's space (coast straight on, actuators centred)."""

    def __init__(self, env: gym.Env):
        self.action = np.zeros(env.action_space.shape, dtype=np.float32)
        self.config: dict = {}

    def act(self, obs: np.ndarray) -> np.ndarray:
        return self.action

    def reset(self, seed: int | None = None) -> None:
        """Deterministic: nothing to seed."""
