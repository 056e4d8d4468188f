"""Policies that fail on purpose, for the evaluation's failure tests: ``tests.agents.faulty:Faulty`` (importable by
spawned workers by that name) and the registered policy ``fragile`` (registered when this module is imported)."""

from __future__ import annotations

import os
from pathlib import Path

from bimp.agents.baselines import LaneKeeping
from bimp.agents.registry import PolicySpec, register_policy


class Faulty:
    """Lane keeping that fails in ``act`` while the file ``flag`` does not exist: ``mode="raise"`` raises,
    ``mode="die"`` ends its process at once (as a segfault or the OOM killer would). ``once``: create the flag
    before failing, so only the first attempt fails."""

    def __init__(self, env, flag: str, mode: str = "raise", once: bool = False):
        self.inner, self.flag, self.mode, self.once = LaneKeeping(env), Path(flag), mode, once
        self.config = {"flag": str(flag), "mode": mode, "once": once}
        self.step_info: dict = {}

    def reset(self, seed=None) -> None:
        self.inner.reset(seed)

    def act(self, obs):
        if not self.flag.exists():
            if self.once:
                self.flag.touch()
            if self.mode == "die":
                os._exit(3)
            raise RuntimeError("injected failure")
        return self.inner.act(obs)


class Fragile(LaneKeeping):
    """Lane keeping that raises in ``act`` when its speed gain exceeds 1 (a tunable policy whose search space
    holds configs that fail: ``fragile``)."""

    def act(self, obs):
        if self.config.k_speed > 1.0:
            raise RuntimeError("injected failure: gain too high")
        return super().act(obs)


def fragile_space() -> dict:
    """Fragile's search space: half of it fails."""
    from optuna.distributions import FloatDistribution

    return {"k_speed": FloatDistribution(0.1, 2.0)}


register_policy(PolicySpec(name="fragile", factory="tests.agents.faulty:Fragile", label="fragile", color="black",
                           search_space="tests.agents.faulty:fragile_space"))
