"""The one protocol every agent implements: planners, the SB3 baseline, simple controllers."""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class Policy(Protocol):
    """What every tool relies on, and nothing more:

    - ``act(obs) -> action`` inside the env's action space (normalized [-1, 1]^2, float32);
    - ``reset(seed)`` at the start of every episode (after ``env.reset``), seeding the policy's own generator so the
      same seed gives the same actions;
    - ``config``: the policy's complete configuration (a dataclass or a dict of plain values), recorded and hashed
      with every episode so a result is attributed to what produced it;
    - ``step_info``: what the last ``act`` did, as a dict (``{"fallback": True}``, a solver's status), recorded per
      step; ``{}`` when there is nothing to say. A batched policy gives one value per row for each key.
    """

    config: Any
    step_info: dict

    def act(self, obs: np.ndarray) -> np.ndarray: ...

    def reset(self, seed: int | None = None) -> None: ...


MEMBERS = ("act", "reset", "config", "step_info")


def missing_members(policy: object) -> list[str]:
    """The members of :class:`Policy` that ``policy`` lacks (``[]`` for a policy)."""
    return [name for name in MEMBERS if not hasattr(policy, name)]
