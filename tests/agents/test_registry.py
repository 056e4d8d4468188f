"""The policy and scenario tables: a new policy or scenario is one module plus one table entry, and `bimp evaluate`
runs it with no other edit; a name registered twice or a malformed entry is refused, naming it."""

import gymnasium as gym
import pytest

import tests.agents.toys  # noqa: F401  (registers the policy "always-brake" and the scenario "gentle-brake")
from bimp import envs
from bimp.agents.cli import main
from bimp.agents.evaluation.records import read_arms, read_records, record_config
from bimp.agents.registry import POLICIES, PolicySpec, make_policy, policy_spec, register_policy
from bimp.envs import SCENARIOS, ScenarioSpec, register_scenario

EVALUATE = ["evaluate", "--scenario", "gentle-brake", "--policy", "always-brake", "--episodes", "2", "--seed", "5",
            "--workers", "1", "--traces", "1"]  # one worker: in this process, where the toys are registered


def test_a_toy_policy_and_scenario_run_through_bimp_evaluate(tmp_path, capsys):
    assert main([*EVALUATE, "--out", str(tmp_path)]) == 0
    records = read_records(tmp_path)
    assert [(r["scenario"], r["policy"], r["seed"], r["status"]) for r in records] == [
        ("gentle-brake", "always-brake", 5, "ok"), ("gentle-brake", "always-brake", 6, "ok")]
    first = records[0]
    config = record_config(first, read_arms(tmp_path))
    assert config["config"] == {"brake": 1.0}
    assert config["scenario"]["brake_decel"] == [2.0, 3.0]  # the toy's own definition, not the parent's
    assert first["policy_info"]["braking_steps"] == list(range(first["steps"]))  # its step_info, every step
    assert first["trace"]["speed"][-1] < first["trace"]["speed"][0]
    assert "| gentle-brake | always-brake | 2 |" in capsys.readouterr().out


def test_the_tables_answer_for_the_toys_and_the_defaults_stay_the_shipped_ones():
    assert envs.env_id("gentle-brake") == "bimp-test/GentleBrake-v0"
    assert envs.scenario_name("bimp-test/GentleBrake-v0") == "gentle-brake"
    assert envs.default_scenarios() == ["overtaking", "emergency-brake"]  # the toy is not a default
    assert gym.make("bimp-test/GentleBrake-v0").spec.max_episode_steps == 120
    assert policy_spec("always-brake").color == "tab:olive" and not policy_spec("always-brake").batched
    assert [n for n, s in POLICIES.items() if s.batched] == ["enkts", "enks"]
    assert {n: s.frontier_axis for n, s in POLICIES.items() if s.frontier_axis} == {
        "enkts": "n_particles", "enks": "n_particles", "mppi": "n_particles", "nmpc": "max_iter", "nmpc-t": "max_iter"}


def test_the_spec_is_what_the_tools_read(tmp_path, capsys):
    assert main([*EVALUATE, "--batch", "2", "--out", str(tmp_path)]) == 2  # not batched in its spec
    assert "--batch needs policies that plan batches; ['always-brake']" in capsys.readouterr().err
    assert main(["tune", "--policy", "always-brake", "--scenario", "gentle-brake", "--out", str(tmp_path)]) == 2
    assert "declares no search space" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_a_factory_whose_object_is_not_a_policy_is_refused_naming_what_it_lacks(tmp_path, capsys):
    with pytest.raises(TypeError, match="lacks step_info of the Policy protocol"):
        make_policy("tests.agents.toys:Mute", gym.make("bimp-test/GentleBrake-v0"))
    argv = ["evaluate", "--scenario", "gentle-brake", "--policy", "tests.agents.toys:Mute", "--out", str(tmp_path)]
    assert main(argv) == 2
    assert "lacks step_info" in capsys.readouterr().err


def test_a_policy_registered_twice_or_malformed_is_refused_naming_it():
    with pytest.raises(ValueError, match="policy 'always-brake' is already registered"):
        register_policy(PolicySpec(name="always-brake", factory="tests.agents.toys:AlwaysBrake", label="x",
                                   color="red"))
    with pytest.raises(ValueError, match="policy 'enkts' is already registered"):
        register_policy(PolicySpec(name="enkts", factory="my.module:make", label="x", color="red"))
    with pytest.raises(ValueError, match="policy spec 'mine' is missing label, color"):
        PolicySpec(name="mine", factory="my.module:make")
    with pytest.raises(ValueError, match="policy spec '\\(no name\\)' is missing name"):
        PolicySpec(factory="my.module:make", label="x", color="red")
    with pytest.raises(ValueError, match="'mine': factory must be a lazy 'module:attr' reference, got 'make_mine'"):
        PolicySpec(name="mine", factory="make_mine", label="x", color="red")
    with pytest.raises(ValueError, match="'mine': search_space must be a lazy"):
        PolicySpec(name="mine", factory="my.module:make", label="x", color="red", search_space="space")
    with pytest.raises(ValueError, match="'mine': batched must be true or false"):
        PolicySpec(name="mine", factory="my.module:make", label="x", color="red", batched="yes")
    with pytest.raises(ValueError, match="'my:mine': a registered name has no ':'"):
        register_policy(PolicySpec(name="my:mine", factory="my.module:make", label="x", color="red"))
    with pytest.raises(TypeError, match="expects a PolicySpec"):
        register_policy({"name": "mine"})
    assert "mine" not in POLICIES and "my:mine" not in POLICIES


def test_a_scenario_registered_twice_or_malformed_is_refused_naming_it():
    spec = dict(entry_point="tests.agents.toys:GentleBrakeEnv", max_episode_steps=120)
    with pytest.raises(ValueError, match="scenario 'gentle-brake' is already registered"):
        register_scenario(ScenarioSpec(name="gentle-brake", id="bimp-test/Other-v0", **spec))
    with pytest.raises(ValueError, match="scenario 'other': id 'bimp/Overtaking-v0' is already registered as "
                                         "scenario 'overtaking'"):
        register_scenario(ScenarioSpec(name="other", id="bimp/Overtaking-v0", **spec))
    with pytest.raises(ValueError, match="scenario spec 'other' is missing entry_point, max_episode_steps"):
        ScenarioSpec(name="other", id="bimp-test/Other-v0")
    with pytest.raises(ValueError, match="'other': max_episode_steps must be an int >= 1, got -5"):
        ScenarioSpec(name="other", id="bimp-test/Other-v0", entry_point=spec["entry_point"], max_episode_steps=-5)
    with pytest.raises(ValueError, match="'other': entry_point must be 'module:Class'"):
        ScenarioSpec(name="other", id="bimp-test/Other-v0", entry_point="GentleBrakeEnv", max_episode_steps=120)
    with pytest.raises(ValueError, match="unknown scenario 'other'"):
        envs.env_id("other")
    assert "other" not in SCENARIOS and "bimp-test/Other-v0" not in gym.registry


def test_a_plain_config_file_goes_on_top_of_a_shipped_tuned_config(tmp_path):
    """``config=PATH`` holding only the horizon kept MPPI's class defaults and dropped its shipped tuned config
    (temperature 1.0 instead of the tuned value): a file of overrides is layered on top, never instead."""
    import gymnasium as gym

    from bimp.agents.evaluation.provenance import resolved_config

    env = gym.make("bimp/EmergencyBrake-v0")
    tuned = resolved_config(make_policy("mppi", env))["config"]
    (tmp_path / "h.yaml").write_text("problem:\n  horizon: 25\n")
    mine = resolved_config(make_policy("mppi", env, config=tmp_path / "h.yaml"))["config"]
    assert mine["problem"]["horizon"] == 25 and tuned["problem"]["horizon"] != 25
    assert {k: v for k, v in mine.items() if k != "problem"} == {k: v for k, v in tuned.items() if k != "problem"}
    assert {k: v for k, v in mine["problem"].items() if k != "horizon"} == \
        {k: v for k, v in tuned["problem"].items() if k != "horizon"}
    assert tuned["temperature"] != 1.0  # the tuned value, not the class default: the test would see the drop
