"""The search space of ``bimp tune`` and the config it edits: a policy's ``{key: optuna distribution}`` checked
against its resolved config, keys as the config names them (``temperature``, ``barrier.edge_margin``, ``sigma_du[1]``,
``problem.sigma_barrier``), and the edits of a config by such keys (``bimp sweep`` uses them too).
"""

from __future__ import annotations

import json
import math
import re
from typing import Any

import gymnasium as gym

from bimp import envs
from bimp.agents import registry
from bimp.agents.evaluation.provenance import resolved_config
from bimp.agents.registry import make_policy, policy_factory


class TuneError(ValueError):
    """A tuning request that cannot run as given (unknown policy, a search-space key its config lacks, results
    seeds)."""



_PART = re.compile(r"([^.\[\]]+)|\[(\d+)\]")


def search_space(policy: str) -> dict:
    """``{key: optuna distribution}`` the policy's spec declares; :class:`TuneError` if it has none."""
    try:
        space = registry.search_space(policy)
    except ValueError as err:
        raise TuneError(str(err)) from None
    if space is None:
        raise TuneError(f"policy {policy!r} declares no search space (the `search_space` of its PolicySpec)")
    return space


def factory_kwargs(policy) -> dict:
    """The keyword arguments that rebuild ``policy`` exactly: its resolved config (a planner's with its
    ``problem``)."""
    return resolved_config(policy)["config"]


def _path(key: str) -> list[str | int]:
    parts = [name if name else int(index) for name, index in _PART.findall(key)]
    if not parts or "".join(f".{p}" if isinstance(p, str) else f"[{p}]" for p in parts).lstrip(".") != key:
        raise TuneError(f"config key {key!r} is not of the form name, name.field or name[index]")
    return parts


def set_value(tree: dict, key: str, value: Any) -> dict:
    """A copy of the nested config ``tree`` (dicts and lists) with ``key`` (``a.b[1]``) set to ``value``;
    :class:`TuneError` naming the key if the config has no such entry."""
    root = json.loads(json.dumps(tree))
    node, part = _entry(root, key)
    node[part] = value
    return root


def get_value(tree: dict, key: str) -> Any:
    """The entry ``key`` (``a.b[1]``) of the nested config ``tree``; :class:`TuneError` naming the key if absent."""
    node, part = _entry(tree, key)
    return node[part]


def _entry(tree: dict, key: str) -> tuple[Any, str | int]:
    """``(container, last part)`` of the entry ``key`` in ``tree``: the dict or list that holds it and its name or
    index there; :class:`TuneError` naming the key, and the part where the path first misses, if absent."""
    parts = _path(key)  # never empty
    node = tree
    for depth, part in enumerate(parts):
        if isinstance(node, dict):
            has = isinstance(part, str) and part in node
        else:
            has = isinstance(node, list) and isinstance(part, int) and part < len(node)
        if not has:
            known = sorted(node) if isinstance(node, dict) else f"{len(node)} entries" if isinstance(node, list) \
                else "no entries"
            where = key if depth == 0 else f"{key} (at {parts[depth]!r})"
            raise TuneError(f"no config entry {where}; the config has {known}")
        if depth < len(parts) - 1:
            node = node[part]
    return node, parts[-1]


def with_params(base: dict, params: dict) -> dict:
    """``base`` (factory kwargs) with every ``key: value`` of ``params`` set."""
    tree = base
    for key, value in params.items():
        tree = set_value(tree, key, value)
    return tree


def overrides_for(base: dict, params: dict) -> dict:
    """The overrides that give ``base`` (factory kwargs) the ``params``: each top-level entry touched, whole."""
    tree = with_params(base, params)
    return {name: tree[name] for name in {_path(key)[0] for key in params}}


def check_space(policy: str, scenarios: list[str], space: dict) -> dict:
    """Validate ``space`` for ``policy`` before any trial: every key names an entry of its config, and the policy
    builds at the low and the high end of every distribution on every scenario. Returns the base: the factory's
    own defaults (not a shipped tuned config, which a study must not drift with), as complete factory kwargs."""
    envs_ = []
    for scenario in scenarios:
        try:
            envs_.append(gym.make(envs.env_id(scenario)))
        except ValueError as err:
            raise TuneError(str(err)) from None
    base = factory_kwargs(policy_factory(policy)(envs_[0]))
    for end in (0, -1):
        params = {k: _ends(d)[end] for k, d in space.items()}
        config = with_params(base, params)  # raises naming a key the config lacks
        for env in envs_:
            try:
                make_policy(policy, env, **config)
            except (ValueError, TypeError) as err:
                raise TuneError(f"{policy} rejects its search space's {'low' if end == 0 else 'high'} end "
                                f"{params}: {err}") from None
    return base


def shipped_params(policy: str, scenario: str, space: dict) -> dict:
    """The values of ``space``'s keys in the config ``policy`` ships with (its shipped tuned config where it has
    one), each that lies in its distribution: a new study's first trial, so that its best is never a config that
    does worse on its training seeds than the one users already run."""
    try:
        shipped = factory_kwargs(make_policy(policy, gym.make(envs.env_id(scenario))))
    except (ValueError, TypeError, OSError) as err:  # a shipped tuned config that no longer builds, say
        raise TuneError(f"{policy}'s shipped config does not build on {scenario}: {err}") from None
    values = {key: get_value(shipped, key) for key in space}
    return {key: value for key, value in values.items() if _contains(space[key], value)}


def _contains(distribution, value) -> bool:
    if hasattr(distribution, "choices"):
        return value in distribution.choices
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    if not distribution.low <= value <= distribution.high:
        return False
    step = getattr(distribution, "step", None)  # a stepped range samples its own grid rather than take a value off it
    return step is None or math.isclose((value - distribution.low) / step, round((value - distribution.low) / step))


def suggest(trial: Any, key: str, distribution: Any) -> Any:
    """``trial.suggest_*`` for an optuna distribution."""
    from optuna.distributions import CategoricalDistribution, IntDistribution

    if isinstance(distribution, CategoricalDistribution):
        return trial.suggest_categorical(key, distribution.choices)
    suggest = trial.suggest_int if isinstance(distribution, IntDistribution) else trial.suggest_float
    return suggest(key, distribution.low, distribution.high, step=distribution.step, log=distribution.log)


def _ends(distribution) -> tuple:
    if hasattr(distribution, "choices"):
        return distribution.choices[0], distribution.choices[-1]
    return distribution.low, distribution.high
