"""highway-env's rule-based driver as a baseline policy (``make_policy("idm", env)``): the reference every
highway-env user knows.

The EV is driven by highway-env's own ``IDMVehicle`` decisions, the behaviour layer of a wrapped env
(:mod:`bimp.envs.highway.behaviour`): IDM for the acceleration, MOBIL for the lane, highway-env's lane-following
steering controller, all as highway-env computes them for its traffic (on exit-v0 the gap plan into the exit lane
replaces MOBIL's lane and IDM's acceleration: :mod:`bimp.envs.highway.gaps`), through the same adapter and action
mapping as every other policy (:meth:`bimp.envs.scene.Scene.to_normalized`: clipped to the actuator range, not to
the planning bounds, as highway-env's driver is unbounded by them; ``clip_to_bounds: true`` clips to the bounds
instead).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np

from bimp.configs import ConfigError, added_field, check_fields, load_config
from bimp.envs.scene import Scene

NEEDS = ("a wrapped highway-env env: bimp.envs.wrap(gym.make(ID)) or gym.make('bimp/ID'), whose behaviour layer "
         "(highway-env's IDM + MOBIL shadowing the EV) it reads")


@dataclass(frozen=True)
class IDMConfig:
    """``clip_to_bounds``: clip highway-env's commands to the scene's planning bounds (default false: only to the
    actuator range, highway-env's driver as it is). ``junction_yield``: drive the behaviour layer's command with its
    yielding at junctions where the road has it (:mod:`bimp.envs.highway.junction`: roundabout-v0, intersection-v0;
    default false: highway-env's driver, which does not yield). A bad value raises
    :class:`bimp.configs.ConfigError`."""

    clip_to_bounds: bool = False
    junction_yield: bool = added_field(False, neutral=False)

    def __post_init__(self) -> None:
        check_fields(self)
        for name in ("clip_to_bounds", "junction_yield"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(name, "true or false", getattr(self, name))


def _adapter(env: gym.Env):
    """The :class:`bimp.envs.highway.adapter.HighwayAdapter` in ``env``'s wrapper chain; ValueError otherwise."""
    current = env
    while current is not None:
        if hasattr(current, "behaviour") and isinstance(getattr(current.unwrapped, "scene", None), Scene):
            return current
        current = getattr(current, "env", None)
    raise ValueError(f"the idm policy needs {NEEDS}; got {type(getattr(env, 'unwrapped', env)).__name__}")


class IDMPolicy:
    """highway-env's IDM + MOBIL driver (see the module docstring). Deterministic: the same observation (and env
    state) gives the same action. ``act(obs)`` returns the driver's command at the env's current state, which
    ``obs`` is the observation of (checked for shape and finiteness)."""

    def __init__(self, env: gym.Env, config: str | Path | None = None, **overrides):
        self.env, self.adapter = env, _adapter(env)
        self.config = load_config(IDMConfig, config, **overrides)
        self.step_info: dict = {}

    def reset(self, seed: int | None = None) -> None:
        """Deterministic: nothing to seed."""

    def act(self, obs: np.ndarray) -> np.ndarray:
        scene = self.env.unwrapped.scene
        scene.check_obs(obs)
        behaviour = self.adapter.behaviour
        command = behaviour.action if self.config.junction_yield else behaviour.own_action
        u = np.array([command["acceleration"], command["steering"]], float)
        if self.config.clip_to_bounds:
            b = scene.bounds
            u = np.array([np.clip(u[0], *b.accel), np.clip(u[1], -b.steer, b.steer)])
        return scene.to_normalized(u).astype(np.float32)
