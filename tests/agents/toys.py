"""A toy policy and a toy scenario, each added with one table entry and nothing else (``tests/agents/test_registry``).
Importing this module registers them."""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np

from bimp.agents.registry import PolicySpec, register_policy
from bimp.envs import ScenarioSpec, register_scenario
from bimp.envs.scenarios import EmergencyBrakeEnv


class AlwaysBrake:
    """Full braking, wheels straight, whatever it sees; it says so at every step."""

    def __init__(self, env: gym.Env, brake: float = 1.0):
        self.action = np.array([-brake, 0.0], dtype=np.float32)  # normalized: -1 is the strongest braking
        self.config = {"brake": brake}
        self.step_info: dict = {}

    def reset(self, seed: int | None = None) -> None:
        self.step_info = {}

    def act(self, obs: np.ndarray) -> np.ndarray:
        self.step_info = {"braking": True}
        return self.action


class Mute(AlwaysBrake):
    """Not a policy: it lacks ``step_info``."""

    def __getattribute__(self, name: str):
        if name == "step_info":
            raise AttributeError(name)
        return super().__getattribute__(name)


class GentleBrakeEnv(EmergencyBrakeEnv):
    """The emergency brake with the OVs braking at 2-3 m/s^2 instead of 5-7."""

    PARAMS = {**EmergencyBrakeEnv.PARAMS,
              "brake_decel": dataclasses.replace(EmergencyBrakeEnv.PARAMS["brake_decel"], default=(2.0, 3.0))}


register_policy(PolicySpec(name="always-brake", factory="tests.agents.toys:AlwaysBrake", label="always brake",
                           color="tab:olive"))
register_scenario(ScenarioSpec(name="gentle-brake", id="bimp-test/GentleBrake-v0",
                               entry_point="tests.agents.toys:GentleBrakeEnv", max_episode_steps=120))
