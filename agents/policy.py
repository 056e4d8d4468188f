"""The one protocol every agent implements: planners, the SB3 baseline, simple controllers."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class Policy(Protocol):
    """``act(obs) -> action`` inside the env's action space (normalized [-1, 1]^2, float32), and
    ``reset(seed)`` at the start of every episode (after ``env.reset``), seeding the policy's own
    generator so the same seed gives the same actions."""

    def act(self, obs: np.ndarray) -> np.ndarray: ...

    def reset(self, seed: int | None = None) -> None: ...
