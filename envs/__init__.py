"""The paper's scenarios as Gymnasium environments. Importing ``bimp`` (or this package) registers them:

>>> import gymnasium as gym, bimp
>>> env = gym.make("bimp/Overtaking-v0", render_mode="rgb_array")
"""

from gymnasium.envs.registration import register, registry

from bimp.envs.road import RoadGeometry
from bimp.envs.scene import Bounds, Scene
from bimp.envs.wrappers import PlanningWrapper

ENV_IDS = {"overtaking": "bimp/Overtaking-v0", "emergency-brake": "bimp/EmergencyBrake-v0"}
# Variants of a scenario under their own id, so that `bimp evaluate --scenario NAME` and its records name them: the
# discovery variant of overtaking (the reference keeps the EV's lane: the planner must find the pass itself).
VARIANT_IDS = {"overtaking-keep-lane": "bimp/OvertakingKeepLane-v0"}
_ENTRY_POINTS = {
    "bimp/Overtaking-v0": ("bimp.envs.scenarios:OvertakingEnv", 150),
    "bimp/EmergencyBrake-v0": ("bimp.envs.scenarios:EmergencyBrakeEnv", 120),
    "bimp/OvertakingKeepLane-v0": ("bimp.envs.scenarios:OvertakingKeepLaneEnv", 150),
}

for _id, (_entry, _steps) in _ENTRY_POINTS.items():
    if _id not in registry:
        register(id=_id, entry_point=_entry, max_episode_steps=_steps)


def env_id(scenario: str) -> str:
    """Gym id of a scenario given by its short name (``overtaking``, ``emergency-brake``, a variant such as
    ``overtaking-keep-lane``) or its id."""
    names = {**ENV_IDS, **VARIANT_IDS}
    if scenario in names.values():
        return scenario
    try:
        return names[scenario]
    except KeyError:
        raise ValueError(f"unknown scenario {scenario!r}; choose from {sorted(names)}") from None


__all__ = ["ENV_IDS", "VARIANT_IDS", "Bounds", "PlanningWrapper", "RoadGeometry", "Scene", "env_id"]
