"""``make_policy(name, env, **overrides)``: every agent by name, built lazily from its module."""

from __future__ import annotations

import importlib
from pathlib import Path

import gymnasium as gym

from bimp.agents.policy import Policy

# Tuned configs written by `bimp tune` (configs/tuned/NAME.yaml): where one ships, it is NAME's default.
TUNED_DIR = Path(__file__).resolve().parent.parent / "configs" / "tuned"

# name -> "module:factory"; each factory takes (env, **overrides) and returns a Policy.
POLICIES = {
    "enkts": "bimp.planners.enkts:make_enkts",
    "enks": "bimp.planners.enkts:make_enks",
    "lane-keep": "bimp.agents.baselines:LaneKeeping",
    "zero": "bimp.agents.baselines:ZeroAction",
    "ppo": "bimp.agents.rl:make_ppo",
    "sac": "bimp.agents.rl:make_sac",
    "mppi": "bimp.planners.mppi:make_mppi",
    "nmpc": "bimp.planners.nmpc:make_nmpc",
    "nmpc-t": "bimp.planners.nmpc:make_nmpc_t",
}


def is_policy_name(name: str) -> bool:
    """A registered name, or ``"package.module:factory"`` (your own policy, built like the registered ones)."""
    return name in POLICIES or (":" in name and all(name.partition(":")[::2]))


def policy_class(name: str):
    """The factory (a class or function) behind ``name``; a factory may declare ``batched = True``."""
    if not is_policy_name(name):
        raise ValueError(f"unknown policy {name!r}; choose from {sorted(POLICIES)} or give 'module:factory'")
    module, factory = POLICIES.get(name, name).split(":")
    return getattr(importlib.import_module(module), factory)


def make_policy(name: str, env: gym.Env, config: str | Path | None = None, **overrides) -> Policy:
    """Build the policy ``name`` for ``env`` (a ``gym.make`` env of this package). ``config``: a YAML written by
    ``bimp tune`` for this policy (default: ``configs/tuned/<name>.yaml`` if one ships), or a plain YAML of
    overrides, handed to the factory as its own ``config``; ``overrides`` go on top, a nested mapping merged key by
    key (``problem={"horizon": 30}`` keeps the rest of a tuned problem), and an unknown key raises.
    ``name`` is a key of ``POLICIES`` or ``"module:factory"``. ``ValueError`` for an unknown name, or a ``config``
    tuned for another policy."""
    factory = policy_class(name)
    if config is None and (TUNED_DIR / f"{name}.yaml").is_file():
        config = TUNED_DIR / f"{name}.yaml"  # a shipped tuned config is the policy's default
    if config is not None:
        from bimp.agents.tune import load_tuned

        tuned = load_tuned(name, config)
        overrides = _merge(tuned, overrides) if tuned is not None else {"config": config, **overrides}
    return factory(env, **overrides)


def _merge(base: dict, top: dict) -> dict:
    """``top`` over ``base``, nested mappings merged key by key."""
    out = dict(base)
    for key, value in top.items():
        out[key] = _merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out
