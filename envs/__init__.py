"""The paper's scenarios as Gymnasium environments. Importing ``bimp`` (or this package) registers them:

>>> import gymnasium as gym, bimp
>>> env = gym.make("bimp/Overtaking-v0", render_mode="rgb_array")

The scenario table: one frozen :class:`ScenarioSpec` per scenario, registered with Gymnasium by
:func:`register_scenario`. Every tool takes its scenario names, its defaults and the name <-> id mapping from it, so a
new scenario is one env class plus one ``register_scenario(ScenarioSpec(...))``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from types import MappingProxyType

from gymnasium.envs.registration import register, registry

from bimp.envs.highway.adapter import PROFILES as _HIGHWAY_PROFILES
from bimp.envs.highway.adapter import entry_name, wrap
from bimp.envs.road import RoadGeometry
from bimp.envs.scene import POLICY_FREQUENCY, Bounds, Scene
from bimp.envs.suite import FAMILIES
from bimp.envs.suite.paper_noisy import FAMILY as PAPER_NOISY
from bimp.envs.traffic import accelerate
from bimp.envs.wrappers import PlanningWrapper


@dataclass(frozen=True, kw_only=True)
class ScenarioSpec:
    """One scenario: its short ``name`` (what ``--scenario`` and the records say), its Gymnasium ``id``, the env
    class as a lazy ``"module:Class"`` ``entry_point``, the episode's ``max_episode_steps``, and whether it is in
    the ``default`` set that the commands run when no ``--scenario`` is given. Every field but ``default`` is
    required; a missing or malformed one is refused naming the scenario."""

    name: str = ""
    id: str = ""
    entry_point: str = ""
    max_episode_steps: int = 0
    default: bool = False
    # The entry point's keyword arguments (a family's difficulty), read-only; left out of the hash as a dict is.
    kwargs: Mapping = field(default_factory=dict, hash=False)

    def __post_init__(self) -> None:
        missing = [f.name for f in fields(self)
                   if f.name not in ("default", "kwargs") and getattr(self, f.name) in ("", 0, None)]
        if missing:
            raise ValueError(f"scenario spec {self.name or '(no name)'!r} is missing {', '.join(missing)}")
        problems = [f"{key} must be a non-empty string, got {value!r}"
                    for key, value in (("name", self.name), ("id", self.id), ("entry_point", self.entry_point))
                    if not isinstance(value, str) or not value.strip()]
        if isinstance(self.name, str) and "/" in self.name:
            problems.append(f"name must not contain '/' (ids do), got {self.name!r}")
        if isinstance(self.entry_point, str) and not all(self.entry_point.partition(":")[::2]):
            problems.append(f"entry_point must be 'module:Class', got {self.entry_point!r}")
        if isinstance(self.max_episode_steps, bool) or not isinstance(self.max_episode_steps, int) \
                or self.max_episode_steps < 1:
            problems.append(f"max_episode_steps must be an int >= 1, got {self.max_episode_steps!r}")
        if not isinstance(self.kwargs, Mapping):
            problems.append(f"kwargs must be a mapping, got {self.kwargs!r}")
        else:
            object.__setattr__(self, "kwargs", MappingProxyType(dict(self.kwargs)))
        if not isinstance(self.default, bool):
            problems.append(f"default must be true or false, got {self.default!r}")
        if problems:
            raise ValueError(f"scenario spec {self.name!r}: {'; '.join(problems)}")


_SCENARIOS: dict[str, ScenarioSpec] = {}
SCENARIOS = MappingProxyType(_SCENARIOS)  # name -> spec, read-only: register_scenario is the one way in


def register_scenario(spec: ScenarioSpec) -> ScenarioSpec:
    """Add ``spec`` to the table and register its id with Gymnasium. ``ValueError`` naming it when its name or id
    is taken (a scenario is defined once)."""
    if not isinstance(spec, ScenarioSpec):
        raise TypeError(f"register_scenario expects a ScenarioSpec, got {spec!r}")
    if spec.name in _SCENARIOS:
        raise ValueError(f"scenario {spec.name!r} is already registered (as {_SCENARIOS[spec.name].id})")
    taken = [s.name for s in _SCENARIOS.values() if s.id == spec.id]
    if taken:
        raise ValueError(f"scenario {spec.name!r}: id {spec.id!r} is already registered as scenario {taken[0]!r}")
    if spec.id not in registry:  # a second copy of this package (a reload) finds its ids already in Gymnasium's
        register(id=spec.id, entry_point=spec.entry_point, max_episode_steps=spec.max_episode_steps,
                 kwargs=dict(spec.kwargs))
    _SCENARIOS[spec.name] = spec
    return spec


# The shipped scenarios. The keep-lane variant of overtaking (the reference keeps the EV's lane: the planner must find
# the pass itself) has its own id so that `bimp evaluate --scenario overtaking-keep-lane` and its records name it.
for _spec in (
    ScenarioSpec(name="overtaking", id="bimp/Overtaking-v0", entry_point="bimp.envs.scenarios:OvertakingEnv",
                 max_episode_steps=150, default=True),
    ScenarioSpec(name="emergency-brake", id="bimp/EmergencyBrake-v0",
                 entry_point="bimp.envs.scenarios:EmergencyBrakeEnv", max_episode_steps=120, default=True),
    ScenarioSpec(name="overtaking-keep-lane", id="bimp/OvertakingKeepLane-v0",
                 entry_point="bimp.envs.scenarios:OvertakingKeepLaneEnv", max_episode_steps=150),
):
    register_scenario(_spec)

# highway-env's envs through the adapter (issue 26): bimp/ID = bimp.envs.wrap(gym.make(ID)) with the adapter's defaults;
# gym.make("bimp/ID", config={...}, n_obstacles=K) passes highway-env's config through. Not in the default set.
# The suite's families (issue 27) run through the same adapter and its table, under their IDs: bimp/stalled-vehicle-v0,
# named by the family (bimp evaluate --scenario stalled-vehicle).
_FAMILY_NAMES = {cls.ID: name for name, cls in FAMILIES.items()}
for _id, _profile in _HIGHWAY_PROFILES.items():
    register_scenario(ScenarioSpec(name=_FAMILY_NAMES.get(_id, _id), id=f"bimp/{_id}",
                                   entry_point=f"bimp.envs.highway.adapter:{entry_name(_id)}",
                                   max_episode_steps=int(round(_profile.duration * POLICY_FREQUENCY))))

# Each family's other difficulties as scenarios of their own, so that every command names them (--scenario cut-in-hard,
# bimp/cut-in-hard-v0: the family's env with config difficulty "hard"); the plain name is the default difficulty.
for _name, _cls in FAMILIES.items():
    for _difficulty in _cls.DIFFICULTIES:
        if _difficulty != _cls.DEFAULT_DIFFICULTY:
            register_scenario(ScenarioSpec(
                name=f"{_name}-{_difficulty}", id=f"bimp/{_name}-{_difficulty}-v0",
                entry_point=f"bimp.envs.highway.adapter:{entry_name(_cls.ID)}",
                max_episode_steps=int(round(_cls.DURATION * POLICY_FREQUENCY)), kwargs={"difficulty": _difficulty}))

# The suite's paper-noisy family (issue 27): the paper's two scenarios with observation noise and a model mismatch, on
# the paper envs' own config (not highway-env's road, so not in FAMILIES, which the adapter wraps); the plain name is
# the default difficulty, the others scenarios of their own as the families' (bimp/overtaking-noisy-hard-v0).
for _cls in PAPER_NOISY:
    for _difficulty in _cls.DIFFICULTIES:
        _suffix = "" if _difficulty == _cls.DEFAULT_DIFFICULTY else f"-{_difficulty}"
        register_scenario(ScenarioSpec(
            name=f"{_cls.NAME}{_suffix}", id=f"bimp/{_cls.NAME}{_suffix}-v0",
            entry_point=f"{_cls.__module__}:{_cls.__name__}",
            max_episode_steps=int(round(_cls.DURATION * POLICY_FREQUENCY)),
            kwargs={"difficulty": _difficulty} if _suffix else {}))

# The shipped scenarios as fixed name -> id views of the table (the default set, and the variants).
ENV_IDS = {s.name: s.id for s in _SCENARIOS.values() if s.default}
VARIANT_IDS = {s.name: s.id for s in _SCENARIOS.values() if not s.default}


def default_scenarios() -> list[str]:
    """The names the commands run when no ``--scenario`` is given (the table's ``default`` entries)."""
    return [s.name for s in _SCENARIOS.values() if s.default]


def scenario_spec(scenario: str) -> ScenarioSpec:
    """The spec of a scenario given by its name or its Gymnasium id; ``ValueError`` naming the choices."""
    spec = _SCENARIOS.get(scenario) or next((s for s in _SCENARIOS.values() if s.id == scenario), None)
    if spec is None:
        raise ValueError(f"unknown scenario {scenario!r}; choose from {sorted(_SCENARIOS)}")
    return spec


def env_id(scenario: str) -> str:
    """Gym id of a scenario given by its short name (``overtaking``, ``emergency-brake``, a variant such as
    ``overtaking-keep-lane``) or its id."""
    return scenario_spec(scenario).id


def scenario_name(gym_id: str) -> str | None:
    """The short name of the scenario registered under ``gym_id``; None for an id outside the table."""
    return next((s.name for s in _SCENARIOS.values() if s.id == gym_id), None)


__all__ = ["ENV_IDS", "SCENARIOS", "VARIANT_IDS", "Bounds", "PlanningWrapper", "RoadGeometry", "Scene", "ScenarioSpec",
           "accelerate", "default_scenarios", "env_id", "register_scenario", "scenario_name", "scenario_spec", "wrap"]
