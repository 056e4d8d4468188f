"""One config shape for every planner (issue 25, item 3): its own fields plus one nested ``problem``, so
``--set POLICY.problem.horizon=25`` means the same for each; the old flat keys are refused naming the new one; the
shipped defaults resolve to the values they had before the change (only the shape moved)."""

from __future__ import annotations

import copy
import dataclasses
import json
import math
from hashlib import sha256
from pathlib import Path

import gymnasium as gym
import pytest

from bimp import envs  # noqa: F401  (registers the envs)
from bimp.agents.baselines import LaneKeepingConfig
from bimp.agents.evaluation.provenance import resolved_config
from bimp.agents.registry import make_policy
from bimp.configs import ConfigError
from bimp.planners.dynamics import WEIGHTS_PATH
from bimp.planners.enkts import EnKTSConfig
from bimp.planners.mppi import MPPIConfig
from bimp.planners.nmpc import NMPCConfig
from bimp.planners.problem import ProblemConfig, load_planner_config, load_problem

PLANNERS = ["enkts", "enks", "mppi", "nmpc", "nmpc-t"]
BEFORE = Path(__file__).with_name("resolved_configs_before_issue25.json")  # make_policy's defaults, old shape


@pytest.fixture(scope="module")
def env():
    return gym.make("bimp/EmergencyBrake-v0")


def migrate(old: dict) -> dict:
    """An old resolved config (``{"config": ..., "tuning": ...}``) in the new shape: what the migration of the
    committed records does. EnKTS/EnKS: the problem's keys move from the top of ``config`` under
    ``config.problem``. MPPI/NMPC: ``tuning`` becomes ``config.problem``; ``config.horizon`` (None: the problem's)
    goes; NMPC's ``nu`` and ``bound_tightening`` replace ``problem.nu`` and ``problem.barrier.bound_margin``.
    Anything else (lane keeping, PPO, zero) is unchanged."""
    config = copy.deepcopy(old["config"])
    if "tuning" in old:
        problem = copy.deepcopy(old["tuning"])
        assert config.pop("horizon", None) in (None, problem["horizon"])  # None meant the problem's
        if "nu" in config:
            problem["nu"] = config.pop("nu")
        if "bound_tightening" in config:
            problem["barrier"]["bound_margin"] = config.pop("bound_tightening")
        config["problem"] = problem
    elif "horizon" in config:
        config["problem"] = {f.name: config.pop(f.name) for f in dataclasses.fields(ProblemConfig) if f.name in config}
    if "problem" in config:  # issue 26 added the general road's window: plain fields, at their defaults
        config["problem"].update(road_points=ProblemConfig.road_points, road_spacing=ProblemConfig.road_spacing)
        # one name per meaning: the barrier's braking of a follower is follower_decel (the env's is brake_decel)
        config["problem"]["barrier"]["follower_decel"] = config["problem"]["barrier"].pop("brake_decel")
        config["problem"]["track_course"] = False  # added since at its neutral value: the planners as they were
    return {"config": config}


@pytest.mark.parametrize("name", [*PLANNERS, "lane-keep"])
def test_the_shipped_defaults_resolve_to_the_values_they_had(env, name):
    old = json.loads(BEFORE.read_text())[name]
    resolved = resolved_config(make_policy(name, env))
    expected = migrate(old)
    if name in ("enkts", "enks"):  # added since: None, the guard where the road asks for it (the paper's does not)
        expected["config"]["road_guard"] = None
    assert {"config": resolved["config"]} == expected
    # Beside the config, only the files it names, by content (issue 28): the shipped weights, for a planner.
    assert resolved.get("files", {}) == ({"problem.dynamics": sha256(WEIGHTS_PATH.read_bytes()).hexdigest()}
                                         if name in PLANNERS else {})


@pytest.mark.parametrize("name", PLANNERS)
def test_problem_horizon_means_the_same_for_every_planner_and_is_recorded(env, name):
    default = resolved_config(make_policy(name, env))["config"]
    for given in ({"problem.horizon": 25}, {"problem": {"horizon": 25}}):  # what --set gives, and a mapping
        policy = make_policy(name, env, **given)
        assert policy.config.problem.horizon == 25
        resolved = resolved_config(policy)
        assert set(resolved) == {"config", "files"}  # one config (the separate `tuning` is gone), and its files
        assert resolved["config"] == {**default, "problem": {**default["problem"], "horizon": 25}}


def test_set_problem_horizon_through_evaluate_is_accepted_and_recorded_for_every_planner():
    from bimp.agents.evaluation.evaluate import resolve_arms

    arms = resolve_arms(["emergency-brake"], PLANNERS, {name: {"problem.horizon": 25} for name in PLANNERS})
    assert [arm.resolved["config"]["problem"]["horizon"] for arm in arms] == [25] * len(PLANNERS)


@pytest.mark.parametrize("name, key, new", [
    ("enkts", "horizon", "problem.horizon"), ("enkts", "nu", "problem.nu"), ("enks", "sigma_du", "problem.sigma_du"),
    ("enkts", "barrier.edge_margin", "problem.barrier.edge_margin"), ("mppi", "horizon", "problem.horizon"),
    ("nmpc", "nu", "problem.nu"), ("nmpc-t", "bound_tightening", "problem.barrier.bound_margin"),
    ("nmpc", "horizon", "problem.horizon")])
def test_an_old_flat_key_is_refused_naming_the_new_one(env, name, key, new):
    with pytest.raises(ValueError, match=f"{key} is now {new} .*--set POLICY.{new}="):
        make_policy(name, env, **{key: 1})


def test_an_old_flat_key_in_a_config_file_is_refused_too(tmp_path, env):
    path = tmp_path / "old.yaml"
    path.write_text("n_particles: 20\nhorizon: 30\n")
    with pytest.raises(ValueError, match="horizon is now problem.horizon"):
        make_policy("enkts", env, config=path)
    path.write_text("n_particles: 20\nproblem: {horizon: 30}\n")
    config = make_policy("enkts", env, config=path).config
    assert (config.n_particles, config.problem.horizon) == (20, 30)
    assert config.problem.sigma_du == load_problem().sigma_du  # the rest of the shared problem, key by key


def test_layers_merge_key_by_key_and_report_nested_errors_with_their_dotted_key():
    config = load_planner_config(MPPIConfig, {"problem": {"barrier": {"headway": 0.9}}}, {"problem.nu": math.inf})
    shared = load_problem()
    assert config.problem == dataclasses.replace(shared, nu=math.inf,
                                                 barrier=dataclasses.replace(shared.barrier, headway=0.9))
    with pytest.raises(ConfigError) as err:
        load_planner_config(EnKTSConfig, {"problem.barrier.edge_margin": "wide"})
    assert err.value.key == "problem.barrier.edge_margin"
    with pytest.raises(ValueError, match="hedway"):
        load_planner_config(NMPCConfig, {"problem.barrier.hedway": 1.0})
    with pytest.raises(ValueError, match="n_particle"):
        load_planner_config(EnKTSConfig, {"n_particle": 10})


def test_every_planner_config_is_frozen_with_one_problem():
    for cls in (EnKTSConfig, MPPIConfig, NMPCConfig):
        config = cls()
        assert isinstance(config.problem, ProblemConfig)
        assert not {f.name for f in dataclasses.fields(ProblemConfig)} & {f.name for f in dataclasses.fields(cls)}
        with pytest.raises(dataclasses.FrozenInstanceError):
            config.problem = ProblemConfig()


def test_lane_keeping_has_a_frozen_checked_config(env):
    policy = make_policy("lane-keep", env, k_lat=0.01)
    assert policy.config == LaneKeepingConfig(k_lat=0.01) and resolved_config(policy) == {
        "config": {"k_lat": 0.01, "k_head": 0.15, "k_speed": 0.8}}
    with pytest.raises(dataclasses.FrozenInstanceError):
        policy.config.k_lat = 0.02
    for bad, key in (({"k_lat": -0.1}, "k_lat"), ({"k_head": "high"}, "k_head"), ({"k_speed": math.inf}, "k_speed")):
        with pytest.raises(ConfigError) as err:
            LaneKeepingConfig(**bad)
        assert err.value.key == key
    with pytest.raises(ValueError, match="k_nope"):
        make_policy("lane-keep", env, k_nope=1.0)


@pytest.mark.parametrize("name", ["mppi", "nmpc-t"])
def test_the_shipped_tuned_configs_load_in_the_new_shape(env, name):
    from bimp.agents.registry import TUNED_DIR
    from bimp.configs import read_overrides

    tuned = read_overrides(TUNED_DIR / f"{name}.yaml")
    assert "horizon" not in tuned and "nu" not in tuned and "bound_tightening" not in tuned
    expected = json.loads(json.dumps(tuned))
    expected["problem"].setdefault("track_course", False)  # added since the tuning, at its neutral value
    assert resolved_config(make_policy(name, env))["config"] == expected
