"""The policy table: one frozen :class:`PolicySpec` per policy, and ``make_policy(name, env, **overrides)``.

Everything a tool needs to know about a policy is in its spec: the factory that builds it, whether it plans batches
(``bimp evaluate --batch``), the search space ``bimp tune`` samples, the config key ``bimp frontier`` trades compute
along, its colour and label in the figures, its config class. The factory, the search space and the config class are
lazy ``"module:attr"`` references, imported on first use: the table costs nothing to load (``bimp --help`` stays
instant) and needs no import of the planners, so no cycle runs through it.

A new policy is one module plus one table entry::

    register_policy(PolicySpec(name="my-planner", factory="my_package.planner:make", label="Mine", color="tab:cyan"))
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any

from bimp.agents.policy import Policy, missing_members
from bimp.configs import TUNED_DIR, check_tuned_for, merged, read_overrides
from bimp.envs.scene import Scene


def _is_reference(value: object) -> bool:
    """``"package.module:attr"`` (``attr`` may be dotted: ``Class.method``)."""
    return isinstance(value, str) and all(value.partition(":")[::2]) and value.count(":") == 1


@dataclass(frozen=True, kw_only=True)
class PolicySpec:
    """One policy. Required: ``name`` (what ``--policy``, records and tuned configs say), ``factory`` (a lazy
    ``"module:attr"`` reference to a callable ``(env, **overrides) -> Policy``), ``label`` and ``color`` (its line
    and legend in the figures, a matplotlib colour). Optional: ``batched`` (the factory also takes a list of envs and
    plans them in one call), ``search_space`` (a lazy reference to a function returning ``{config key: optuna
    distribution}``, for ``bimp tune``), ``frontier_axis`` (the config key that buys quality with compute, for
    ``bimp frontier``), ``config_class`` (a lazy reference to the policy's config dataclass). A missing or
    malformed field is refused naming the policy."""

    name: str = ""
    factory: str = ""
    label: str = ""
    color: str = ""
    batched: bool = False
    search_space: str | None = None
    frontier_axis: str | None = None
    config_class: str | None = None

    def __post_init__(self) -> None:
        required = ("name", "factory", "label", "color")
        missing = [key for key in required if getattr(self, key) in ("", None)]
        if missing:
            raise ValueError(f"policy spec {self.name or '(no name)'!r} is missing {', '.join(missing)}")
        problems = [f"{key} must be a non-empty string, got {getattr(self, key)!r}" for key in required
                    if not isinstance(getattr(self, key), str) or not getattr(self, key).strip()]
        problems += [f"{key} must be a lazy 'module:attr' reference, got {getattr(self, key)!r}"
                     for key in ("factory", "search_space", "config_class")
                     if getattr(self, key) is not None and not _is_reference(getattr(self, key))]
        if not isinstance(self.batched, bool):
            problems.append(f"batched must be true or false, got {self.batched!r}")
        if self.frontier_axis is not None and not (isinstance(self.frontier_axis, str) and self.frontier_axis):
            problems.append(f"frontier_axis must be a config key or None, got {self.frontier_axis!r}")
        if problems:
            raise ValueError(f"policy spec {self.name!r}: {'; '.join(problems)}")


def load(reference: str) -> Any:
    """The object a lazy ``"module:attr"`` reference names (``attr`` may be dotted), importing its module."""
    module, _, attr = reference.partition(":")
    value: Any = importlib.import_module(module)
    for part in attr.split("."):
        value = getattr(value, part)
    return value


_POLICIES: dict[str, PolicySpec] = {}
POLICIES = MappingProxyType(_POLICIES)  # name -> spec, read-only: register_policy is the one way in


def register_policy(spec: PolicySpec) -> PolicySpec:
    """Add ``spec`` to the table; ``ValueError`` naming it when its name is taken (a policy is defined once)."""
    if not isinstance(spec, PolicySpec):
        raise TypeError(f"register_policy expects a PolicySpec, got {spec!r}")
    if ":" in spec.name or "/" in spec.name:  # a name with ':' means "module:factory"; '/' would split a folder
        raise ValueError(f"policy spec {spec.name!r}: a registered name has no ':' or '/'")
    if spec.name in _POLICIES:
        raise ValueError(f"policy {spec.name!r} is already registered (factory {_POLICIES[spec.name].factory})")
    _POLICIES[spec.name] = spec
    return spec


_ENKTS, _MPPI, _NMPC = "bimp.planners.enkts", "bimp.planners.mppi", "bimp.planners.nmpc"
for _spec in (
    PolicySpec(name="enkts", factory=f"{_ENKTS}:make_enkts", label="EnKTS", color="tab:red", batched=True,
               search_space=f"{_ENKTS}:search_space", frontier_axis="n_particles",
               config_class=f"{_ENKTS}:EnKTSConfig"),
    PolicySpec(name="enks", factory=f"{_ENKTS}:make_enks", label="EnKS", color="tab:blue", batched=True,
               search_space=f"{_ENKTS}:enks_search_space", frontier_axis="n_particles",
               config_class=f"{_ENKTS}:EnKTSConfig"),
    PolicySpec(name="mppi", factory=f"{_MPPI}:make_mppi", label="MPPI", color="tab:green",
               search_space=f"{_MPPI}:search_space", frontier_axis="n_particles", config_class=f"{_MPPI}:MPPIConfig"),
    PolicySpec(name="nmpc", factory=f"{_NMPC}:make_nmpc", label="NMPC", color="tab:purple",
               search_space=f"{_NMPC}:search_space", frontier_axis="max_iter", config_class=f"{_NMPC}:NMPCConfig"),
    PolicySpec(name="nmpc-t", factory=f"{_NMPC}:make_nmpc_t", label="NMPC-t", color="tab:pink",
               search_space=f"{_NMPC}:nmpc_t_search_space", frontier_axis="max_iter",
               config_class=f"{_NMPC}:NMPCConfig"),
    PolicySpec(name="ppo", factory="bimp.agents.rl:make_ppo", label="PPO", color="tab:orange"),
    PolicySpec(name="sac", factory="bimp.agents.rl:make_sac", label="SAC", color="tab:brown"),
    PolicySpec(name="lane-keep", factory="bimp.agents.baselines:LaneKeeping", label="lane keeping", color="tab:gray",
               search_space="bimp.agents.baselines:search_space",
               config_class="bimp.agents.baselines:LaneKeepingConfig"),
    PolicySpec(name="zero", factory="bimp.agents.baselines:ZeroAction", label="zero action", color="black"),
    # highway-env's rule-based driver (IDM + MOBIL + its steering controller) on a wrapped highway-env env
    PolicySpec(name="idm", factory="bimp.agents.idm:IDMPolicy", label="IDM/MOBIL", color="tab:olive",
               config_class="bimp.agents.idm:IDMConfig"),
):
    register_policy(_spec)


def is_policy_name(name: str) -> bool:
    """A registered name, or ``"package.module:factory"`` (your own policy, built like the registered ones)."""
    return name in _POLICIES or _is_reference(name)


def policy_spec(name: str) -> PolicySpec:
    """The spec of ``name``; for a ``"module:factory"`` name, a plain one (not batched, nothing to tune, no
    frontier axis, drawn in black under its own name). ``ValueError`` for an unknown name."""
    if name in _POLICIES:
        return _POLICIES[name]
    if _is_reference(name):
        return PolicySpec(name=name, factory=name, label=name, color="black")
    raise ValueError(f"unknown policy {name!r}; choose from {sorted(_POLICIES)} or give 'module:factory'")


def policy_factory(name: str):
    """The factory (a class or function) behind ``name``; ``ValueError`` for an unknown name."""
    return load(policy_spec(name).factory)


def search_space(name: str) -> dict | None:
    """``{config key: optuna distribution}`` that ``bimp tune`` samples for ``name``; None if it declares none."""
    spec = policy_spec(name)
    return None if spec.search_space is None else dict(load(spec.search_space)())


def policy_color(name: str) -> str:
    """The colour of ``name`` in the figures (black for a name outside the table, such as a ``--label``)."""
    spec = _POLICIES.get(name)
    return spec.color if spec else "black"


def policy_label(name: str) -> str:
    """The legend of ``name`` in the figures: its spec's label, or ``name`` itself outside the table."""
    spec = _POLICIES.get(name)
    return spec.label if spec else name


def check_env(env) -> None:
    """``ValueError`` unless ``env`` (or each env of a list) publishes ``env.unwrapped.scene`` as a bimp
    :class:`~bimp.envs.scene.Scene`, what every policy plans on: a raw highway-env env, a discrete-action env or an
    env of another package is refused, saying what it needs."""
    for one in env if isinstance(env, (list, tuple)) else [env]:
        if not isinstance(getattr(getattr(one, "unwrapped", None), "scene", None), Scene):
            raise ValueError(f"{type(getattr(one, 'unwrapped', one)).__name__} is not a bimp env: every policy needs "
                             "a bimp env: wrap a highway-env env with bimp.envs.wrap(env) (or make it with "
                             "gym.make('bimp/ID')), or use a bimp scenario (gym.make('bimp/Overtaking-v0'))")


def make_policy(name: str, env, config: str | Path | None = None, **overrides) -> Policy:
    """Build the policy ``name`` for ``env`` (a ``gym.make`` env of this package), configured in layers, each a
    YAML of overrides over the one before: the policy's shipped tuned config (``configs/tuned/<name>.yaml``) where
    one ships, ``config`` (one written by ``bimp tune``, or any file of overrides), then ``overrides``; nested
    mappings merge key by key (``problem={"horizon": 30}`` keeps the rest of a tuned problem) and an unknown key
    raises. Without a shipped tuned config the factory takes ``config`` as its own layer, on top of its defaults.
    ``name`` is a key of ``POLICIES`` or ``"module:factory"``. ``ValueError`` for an unknown name, or a ``config``
    tuned for another policy (its ``NAME.tuning.yaml`` says so); ``TypeError`` for a factory whose policy lacks a
    member of :class:`Policy`."""
    factory = policy_factory(name)
    check_env(env)
    given = None
    if config is not None:  # read here, whatever the factory does with it: a bad file is refused naming it
        check_tuned_for(name, config)
        given = read_overrides(config)
    shipped = TUNED_DIR / f"{name}.yaml"
    if shipped.is_file():  # a shipped tuned config is the default; a config file goes on top of it, never instead
        overrides = merged(merged(read_overrides(shipped), given or {}), overrides)
    elif config is not None:
        overrides = {"config": config, **overrides}
    policy = factory(env, **overrides)
    missing = missing_members(policy)
    if missing:  # refused here, where the name is known, not as an AttributeError inside an episode
        raise TypeError(f"policy {name!r} ({type(policy).__name__}) lacks {', '.join(missing)} of the Policy "
                        "protocol (bimp.agents.policy)")
    return policy


__all__ = ["POLICIES", "PolicySpec", "is_policy_name", "load", "make_policy", "policy_color", "policy_factory",
           "policy_label", "policy_spec", "register_policy", "search_space"]
