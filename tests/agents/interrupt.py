"""Training cut short as an interruption cuts it, for the resume tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from bimp.agents import rl, rl_train


def interrupted_run(cfg: rl.RLConfig, out: Path, monkeypatch: pytest.MonkeyPatch, after: int) -> None:
    """Train ``cfg`` into ``out`` until a KeyboardInterrupt past ``after`` timesteps (raised through the progress
    bar's callback), as Ctrl-C or a killed session leaves a run."""
    from stable_baselines3.common.callbacks import BaseCallback

    class Interrupt(BaseCallback):
        def _on_step(self) -> bool:
            if self.num_timesteps > after:
                raise KeyboardInterrupt
            return True

    with monkeypatch.context() as patch:
        patch.setattr(rl_train, "_progress_callback", lambda total: Interrupt())
        with pytest.raises(KeyboardInterrupt):
            rl_train.train(cfg, out, progress=True)
