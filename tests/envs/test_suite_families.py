"""What every scenario family of the suite must do alike, tested on each entry of the suite's table: the same seed
gives the same episode and another seed another; idm and enkts drive a short seeded hard episode; the ranges table of
its module docstring is its ``DIFFICULTIES``. Also the oracle's
plan as a policy, which each family's own tests drive through its env."""

from __future__ import annotations

import dataclasses
import re
import sys

import gymnasium as gym
import numpy as np
import pytest

import bimp  # registers bimp/<family>-v0
from bimp import make_policy
from bimp.envs.scene import Bounds
from bimp.envs.suite import FAMILIES
from bimp.envs.suite.family import HighwayFamily

pytestmark = pytest.mark.filterwarnings("ignore")
IDS = [f"bimp/{cls.ID}" for cls in FAMILIES.values()]
B = Bounds()


class BrakeAtTheBounds:
    """The oracle's plan as a policy: straight on, the acceleration ramped to a_min by the rate bound from step 1."""

    def __init__(self, env):
        self.env, self.a, self.step_info = env, 0.0, {}

    def reset(self, seed: int | None = None) -> None:
        self.a = 0.0

    def act(self, obs):
        self.a = max(self.a - B.accel_rate, B.accel[0])
        return self.env.unwrapped.scene.to_normalized(np.array([self.a, 0.0])).astype(np.float32)


def drive_the_oracles_plan(env_id: str, config: dict, standing, seeds=range(100)) -> tuple[list[int], set[int]]:
    """The oracle's plan (:class:`BrakeAtTheBounds`) driven for whole episodes of ``gym.make(env_id, config=config)``
    on ``seeds``, asserting no collision at the EV's fault. ``standing(env.unwrapped)``: what stands in the EV's lane
    ahead, nearest first (the stall, or the closure's blocks). Returns the seeds where the EV was struck (never its
    fault: rear-ended) and those where other traffic entered the EV's lane between it and the nearest standing
    vehicle while the EV still moved (the oracle assumes none does)."""
    from bimp.agents.evaluation.metrics import contact_at_fault

    env = gym.make(env_id, config=config)
    rear_ended, entered = [], set()
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        base = env.unwrapped
        ev, stand, policy = base.vehicle, list(standing(base)), BrakeAtTheBounds(env)
        while True:
            moving = ev.speed > 0.0
            obs, _, terminated, truncated, info = env.step(policy.act(obs))
            if moving and any(v is not ev and v not in stand and v.lane_index == ev.lane_index
                              and ev.position[0] < v.position[0] < stand[0].position[0] for v in base.road.vehicles):
                entered.add(seed)
            if info["collision"]:
                assert info["contact"] is not None and not contact_at_fault(info["contact"]), seed
                rear_ended.append(seed)
            if terminated or truncated:
                break
    return rear_ended, entered


def drawn_params(env_id: str, config: dict | None = None, n: int = 1000) -> list[dict]:
    """The drawn parameters of ``reset(seed=k)``, k < ``n``, of ``gym.make(env_id, config=config)``: a family's own
    draws, in its order, for its oracle tests."""
    base = gym.make(env_id, config=config).unwrapped
    out = []
    for seed in range(n):
        base.reset(seed=seed)
        out.append(dict(base.drawn_params))
    return out


@pytest.mark.parametrize("env_id", IDS)
def test_same_seed_same_observations_and_other_seeds_differ(env_id):
    runs = []
    for seed in (3, 3, 4):
        env = gym.make(env_id)
        obs, _ = env.reset(seed=seed)
        seq = [obs]
        for k in range(10):
            obs, *_ = env.step(np.array([0.1, 0.01 * np.sin(k)], np.float32))
            seq.append(obs)
        runs.append((np.array(seq), dict(env.unwrapped.drawn_params)))
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    assert runs[0][1] == runs[1][1]
    assert runs[0][1] != runs[2][1] and not np.array_equal(runs[0][0], runs[2][0])


@pytest.mark.parametrize("env_id", IDS)
@pytest.mark.parametrize("policy", ["idm", "enkts"])
def test_short_seeded_episode(env_id, policy):
    env = gym.make(env_id, config={"difficulty": "hard"})
    agent = make_policy(policy, env)
    obs, info = env.reset(seed=1)
    agent.reset(1)
    for _ in range(10):
        action = agent.act(obs)
        assert action.shape == (2,) and np.all(np.isfinite(action)) and np.all(np.abs(action) <= 1.0)
        obs, _, terminated, truncated, info = env.step(action)
        assert np.all(np.isfinite(obs)) and not info["collision"] and not info["offroad"]
        if terminated or truncated:
            break


@pytest.mark.parametrize("name", list(FAMILIES))
def test_every_difficulty_is_a_scenario_of_its_own(name):
    """``--scenario cut-in-hard`` (``bimp/cut-in-hard-v0``): the family at that difficulty, its ranges the preset's
    unless a range key overrides one; the plain name is the default difficulty; a contradicting difficulty is
    refused."""
    cls = FAMILIES[name]
    assert bimp.envs.env_id(name) == f"bimp/{cls.ID}"
    for difficulty, preset in cls.DIFFICULTIES.items():
        scenario = name if difficulty == cls.DEFAULT_DIFFICULTY else f"{name}-{difficulty}"
        spec = bimp.envs.scenario_spec(scenario)
        assert spec.max_episode_steps == round(cls.DURATION * 10)
        config = gym.make(spec.id).unwrapped.config
        assert config["difficulty"] == difficulty
        assert {k: tuple(config[k]) for k in cls.range_keys()} == dataclasses.asdict(preset)
    hard = bimp.envs.env_id(f"{name}-hard")
    key = cls.range_keys()[0]
    lo, hi = cls.DIFFICULTIES["hard"].__dict__[key]
    config = gym.make(hard, config={key: hi}).unwrapped.config
    assert config["difficulty"] == "hard" and tuple(config[key]) == (hi, hi)
    with pytest.raises(ValueError, match="difficulty must be 'hard', the difficulty this id names"):
        gym.make(hard, config={"difficulty": "easy"})
    env = gym.make(hard)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="difficulty must be 'hard'"):  # nor at a reset: never another's episodes
        env.reset(seed=0, options={"config": {"difficulty": "easy"}})
    assert env.unwrapped.config["difficulty"] == "hard"


def _range_key(keys: tuple[str, ...], column: str) -> str:
    """The range key a docstring table's column names: the key itself, else the one key it starts."""
    if column in keys:
        return column
    (key,) = [k for k in keys if k.startswith(column)]
    return key


@pytest.mark.parametrize("name", list(FAMILIES))
def test_the_docstrings_table_is_the_difficulties(name):
    """The ranges table in each family's module docstring (what a user reads first) says what ``DIFFICULTIES``
    holds: one row per difficulty, each column a range key (its name or the start of it), each cell ``lo - hi``."""
    cls = FAMILIES[name]
    doc = sys.modules[cls.__module__].__doc__
    rule, header, body = re.search(r"\n(=+(?:  +=+)+)\n(.*?)\n\1\n(.*?)\n\1\n", doc, re.S).groups()
    keys = [_range_key(cls.range_keys(), column) for column in header.split()[1:]]
    assert len(set(keys)) == len(keys), keys
    rows = {}
    for line in body.splitlines():
        difficulty, *cells = re.split(r"\s{2,}", line.strip())
        rows[difficulty] = {k: tuple(float(x) for x in cell.split(" - ")) for k, cell in zip(keys, cells, strict=True)}
    assert list(rows) == list(cls.DIFFICULTIES)
    for difficulty, preset in cls.DIFFICULTIES.items():
        assert rows[difficulty] == {k: tuple(getattr(preset, k)) for k in keys}, difficulty


@pytest.mark.parametrize("name", list(FAMILIES))
def test_what_every_family_refuses_naming_the_key(name):
    """An unknown difficulty (at gym.make and at a reset), an unknown key, a highway-env key the family's draws
    replace, another duration, and on highway-env's straight road fewer than 2 lanes: ValueError naming it. A preset
    is a valid ranges object of its own."""
    cls = FAMILIES[name]
    env_id = f"bimp/{cls.ID}"
    rows = [({"difficulty": "no-such-level"}, "difficulty"), ({"difficulty": 2}, "difficulty"),
            ({"no_such_key": 1}, "no_such_key"), ({"duration": cls.DURATION + 10}, "duration"),
            *(({key: 1}, key) for key in sorted(cls.REMOVED_KEYS))]
    if issubclass(cls, HighwayFamily):
        rows.append(({"lanes_count": 1}, "lanes_count"))
    for config, match in rows:
        with pytest.raises(ValueError, match=match):
            gym.make(env_id, config=config)
    env = gym.make(env_id)
    with pytest.raises(ValueError, match="difficulty"):
        env.reset(seed=0, options={"config": {"difficulty": "insane"}})
    for preset in cls.DIFFICULTIES.values():
        assert cls.RANGES(**dataclasses.asdict(preset)) == preset
