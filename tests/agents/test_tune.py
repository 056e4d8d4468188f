"""``bimp tune``: Optuna studies over a policy's declared search space, on training seeds only."""

import dataclasses
import time

import gymnasium as gym
import optuna
import pytest
import yaml

import bimp.agents.baselines
import tests.agents.faulty  # noqa: F401  (registers the policy "fragile")
from bimp import envs  # noqa: F401  (registers the envs)
from bimp.agents.baselines import LaneKeeping
from bimp.agents.evaluation.tune import (
    TuneError,
    check_space,
    get_value,
    objective_value,
    search_space,
    set_value,
    tune,
)
from bimp.agents.registry import POLICIES, TUNED_DIR, make_policy
from bimp.configs import TUNING_SUFFIX, tuning_path

EB = ["emergency-brake"]
SMALL = dict(scenarios=EB, episodes=2, progress=False)


def _run(tmp_path, trials, policy="lane-keep", **kw):
    return tune(policy, trials=trials, out=tmp_path / "study", yaml_path=tmp_path / "best.yaml", **{**SMALL, **kw})


def test_a_two_trial_study_writes_a_study_and_a_config_that_make_policy_loads(tmp_path):
    study = tune("lane-keep", trials=2, out=tmp_path / "study", **SMALL)  # the best config: OUT/best.yaml
    (tmp_path / "study" / "best.yaml").rename(tmp_path / "best.yaml")
    assert (tmp_path / "study" / "study.db").is_file()
    assert [t.state for t in study.trials] == [optuna.trial.TrialState.COMPLETE] * 2
    # The study records each trial's folder relative to itself: no path of the machine it ran on (issue 28).
    assert all((tmp_path / "study" / t.user_attrs["folder"] / "episodes.jsonl").is_file()
               and str(tmp_path) not in t.user_attrs["folder"] for t in study.trials)
    (tmp_path / "study" / "best.tuning.yaml").rename(tmp_path / "best.tuning.yaml")
    # One shape: the file is the config alone (what any file of overrides is); its tuning lies beside it.
    assert yaml.safe_load((tmp_path / "best.yaml").read_text()) == pytest.approx(study.best_trial.params)
    doc = yaml.safe_load((tmp_path / "best.tuning.yaml").read_text())
    assert doc["policy"] == "lane-keep" and doc["tuning"]["trial"] == study.best_trial.number
    policy = make_policy("lane-keep", gym.make("bimp/EmergencyBrake-v0"), config=tmp_path / "best.yaml")
    assert dataclasses.asdict(policy.config) == pytest.approx(study.best_trial.params)
    # An override still wins over the tuned value.
    policy = make_policy("lane-keep", gym.make("bimp/EmergencyBrake-v0"), config=tmp_path / "best.yaml", k_lat=0.01)
    assert policy.config.k_lat == 0.01


def test_a_resumed_study_continues_its_trial_count_with_fresh_values(tmp_path):
    first = [t.params for t in _run(tmp_path, 2).trials]
    study = _run(tmp_path, 3)
    assert [t.number for t in study.trials] == [0, 1, 2]
    assert [t.params for t in study.trials[:2]] == first  # not rerun
    assert study.trials[2].params not in first
    assert len(_run(tmp_path, 3).trials) == 3  # a finished study runs nothing more


# optuna flags the heartbeat experimental, and a trial asked outside optimize, as the killed one is here
@pytest.mark.filterwarnings("ignore::optuna.exceptions.ExperimentalWarning", "ignore:Heartbeat of storage")
def test_a_trial_retried_after_its_process_died_does_not_cost_the_study_a_trial(tmp_path, monkeypatch):
    """A process killed mid-trial leaves it RUNNING, its heartbeat stopped; the resumed run fails it and retries its
    values (optuna's RetryHeartbeatStaleTrialCallback). Resumed with --trials 4 after two trials and a dead third,
    the study runs the retry and one new trial: four trials that ran to the end, not three. The heartbeat's grace
    shortened from 90 s to 2 s so that the test need not wait."""
    from optuna.storages import RetryHeartbeatStaleTrialCallback

    import bimp.agents.evaluation.tune as tune_module

    def storage(url):
        return optuna.storages.RDBStorage(url, heartbeat_interval=1, grace_period=2,
                                          heartbeat_stale_trial_callback=RetryHeartbeatStaleTrialCallback(1))

    monkeypatch.setattr(tune_module, "_storage", storage)
    first = _run(tmp_path, 2)
    dead = first.ask()  # the killed process's trial: values drawn, a heartbeat recorded, never told
    for key, distribution in search_space("lane-keep").items():
        tune_module.suggest(dead, key, distribution)
    first._storage.record_heartbeat(dead._trial_id)
    time.sleep(3)  # past the grace
    study = _run(tmp_path, 4)
    assert [t.state.name for t in study.trials] == ["COMPLETE", "COMPLETE", "FAIL", "COMPLETE", "COMPLETE"]
    assert study.trials[3].params == study.trials[2].params != study.trials[4].params  # the retry, then a new one
    assert len(_run(tmp_path, 4).trials) == 5  # done: a rerun runs nothing more


def test_a_new_studys_first_trial_is_the_shipped_config_and_a_resumed_one_keeps_its_first(tmp_path, monkeypatch):
    import bimp.agents.registry

    env = gym.make("bimp/EmergencyBrake-v0")
    shipped = dataclasses.asdict(make_policy("lane-keep", env).config)
    assert _run(tmp_path, 1).trials[0].params == pytest.approx(shipped)
    # A shipped tuned config is what users run, so it is the first trial; a value outside the space is sampled.
    monkeypatch.setattr(bimp.agents.registry, "TUNED_DIR", tmp_path)
    tuned = {**shipped, "k_lat": 0.015, "k_head": 5.0}
    (tmp_path / "lane-keep.yaml").write_text(yaml.safe_dump(tuned))
    first = _run(tmp_path / "tuned", 2).trials
    assert first[0].params["k_lat"] == 0.015 and first[0].params["k_head"] <= 0.5
    assert first[0].params["k_speed"] == pytest.approx(shipped["k_speed"])
    assert first[1].params != first[0].params
    assert _run(tmp_path / "tuned", 3).trials[0].params == first[0].params  # resumed: not enqueued again


def test_a_shipped_value_is_enqueued_only_where_the_space_could_have_drawn_it():
    from optuna.distributions import CategoricalDistribution, FloatDistribution, IntDistribution

    from bimp.agents.evaluation.tune_space import _contains

    assert _contains(IntDistribution(1, 5), 3) and not _contains(IntDistribution(1, 5), True)
    assert _contains(FloatDistribution(0.0, 1.0, step=0.25), 0.5)
    assert not _contains(FloatDistribution(0.0, 1.0, step=0.25), 0.3)  # off the grid
    assert _contains(FloatDistribution(0.1, 1.0, log=True), 0.5) and not _contains(FloatDistribution(0.0, 1.0), 2.0)
    assert _contains(CategoricalDistribution([2, 4, 6]), 4) and not _contains(CategoricalDistribution([2, 4, 6]), 3)


def test_a_trial_whose_episodes_raise_fails_with_its_error_and_the_study_goes_on(tmp_path):
    study = _run(tmp_path, 6, policy="fragile")
    states = {t.state for t in study.trials}
    assert len(study.trials) == 6 and states == {optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.FAIL}
    for t in study.trials:
        failed = t.state == optuna.trial.TrialState.FAIL
        assert failed == (t.params["k_speed"] > 1.0)
        assert ("injected failure" in t.user_attrs.get("error", "")) == failed
    assert study.best_trial.params["k_speed"] <= 1.0


TUNABLE = sorted(name for name, spec in POLICIES.items() if spec.search_space and name != "fragile")


def test_every_planner_declares_a_search_space():
    assert {"enkts", "enks", "mppi", "nmpc", "nmpc-t", "lane-keep"} <= set(TUNABLE)


@pytest.mark.parametrize("policy", TUNABLE)
def test_every_search_space_names_only_keys_its_config_accepts(policy):
    space = search_space(policy)
    check_space(policy, ["overtaking"], space)  # raises naming a key the config lacks, or a value it rejects
    assert space


def test_a_shipped_tuned_config_is_the_default_and_a_study_does_not_drift_with_it(tmp_path, monkeypatch):
    import bimp.agents.registry

    study = _run(tmp_path, 2)
    monkeypatch.setattr(bimp.agents.registry, "TUNED_DIR", tmp_path)
    (tmp_path / "best.yaml").rename(tmp_path / "lane-keep.yaml")
    (tmp_path / "best.tuning.yaml").rename(tmp_path / "lane-keep.tuning.yaml")
    env = gym.make("bimp/EmergencyBrake-v0")
    assert dataclasses.asdict(make_policy("lane-keep", env).config) == pytest.approx(study.best_trial.params)
    # The study's base is the factory's own defaults: a resumed study runs its trials as before.
    base = check_space("lane-keep", EB, search_space("lane-keep"))
    assert base == dataclasses.asdict(LaneKeeping(env).config)


def test_make_policy_refuses_a_config_tuned_for_another_policy_and_passes_a_plain_one_on(tmp_path):
    _run(tmp_path, 1)
    env = gym.make("bimp/EmergencyBrake-v0")
    with pytest.raises(ValueError, match="tuned for 'lane-keep', not 'enkts'"):
        make_policy("enkts", env, config=tmp_path / "best.yaml")
    (tmp_path / "plain.yaml").write_text("n_particles: 20\n")  # the factory's own YAML of overrides
    assert make_policy("enkts", env, config=tmp_path / "plain.yaml").config.n_particles == 20


def test_an_override_of_a_nested_entry_keeps_the_rest_of_the_tuned_config():
    tuned = yaml.safe_load((TUNED_DIR / "mppi.yaml").read_text())["problem"]
    policy = make_policy("mppi", gym.make("bimp/Overtaking-v0"), problem={"horizon": 30})
    assert policy.config.problem.horizon == 30
    assert policy.config.problem.sigma_barrier == tuned["sigma_barrier"] != 0.1  # tuned, not the shared problem's
    assert policy.config.problem.barrier.headway == tuned["barrier"]["headway"]


def test_bad_requests_fail_before_any_trial(tmp_path, monkeypatch):
    with pytest.raises(TuneError, match="unknown policy"):
        _run(tmp_path, 1, policy="nope")
    with pytest.raises(TuneError, match="declares no search space"):
        _run(tmp_path, 1, policy="zero")
    with pytest.raises(TuneError, match="never tuned on"):
        _run(tmp_path, 1, seed=999)  # seeds 999 and 1000: the second is a results seed
    space = {**bimp.agents.baselines.search_space(), "k_nope": optuna.distributions.FloatDistribution(0, 1)}
    monkeypatch.setattr(bimp.agents.baselines, "search_space", lambda: space)
    with pytest.raises(TuneError, match="k_nope"):
        _run(tmp_path, 1)
    assert not (tmp_path / "study").exists()


def test_set_value_and_get_value_walk_nested_entries_and_name_a_missing_one():
    tree = {"a": 1, "barrier": {"widths": [1, 2, 3]}, "sigma": [0.1, 0.2]}
    assert set_value(tree, "barrier.widths[2]", 9)["barrier"]["widths"] == [1, 2, 9]
    assert set_value(tree, "sigma[0]", 5)["sigma"] == [5, 0.2] and tree["sigma"] == [0.1, 0.2]
    assert get_value(tree, "barrier.widths[2]") == 3 and get_value(tree, "barrier") == {"widths": [1, 2, 3]}
    for key, missing in (("barrier.height", "height"), ("sigma[2]", "2"), ("a.b", "b"), ("nope", "nope"),
                         ("sigma.x", "x"), ("barrier[0]", "0")):
        for walk in (lambda: set_value(tree, key, 0), lambda: get_value(tree, key)):
            with pytest.raises(TuneError, match=rf"no config entry .*{missing}"):
                walk()


def _summary(success, collision, offroad, violation, n=10):
    rate = {"success_rate": success, "collision_rate": collision, "offroad_rate": offroad,
            "input_violation_rate": violation, "rate_violation_rate": violation}
    return {"arm": {"episodes": n, **{k: {"mean": v} for k, v in rate.items()}}}


def test_the_objective_is_success_first_then_collisions_then_off_road_then_violations():
    ranked = [_summary(0.9, 1.0, 1.0, 1.0),  # one success more outweighs every tie-break
              _summary(0.8, 0.0, 1.0, 1.0),
              _summary(0.8, 0.1, 0.0, 1.0),
              _summary(0.8, 0.1, 0.1, 0.0),
              _summary(0.8, 0.1, 0.1, 0.5)]
    values = [objective_value(s) for s in ranked]
    assert values == sorted(values, reverse=True) and len(set(values)) == len(values)


def test_the_score_objective_is_the_pooled_mean_score_and_its_own_study(tmp_path):
    """--objective score: a trial's value is the mean closed-loop score over every episode of every scenario (pooled
    by episodes); the best config records which objective chose it; a study of another objective never resumes
    onto the success study's trials."""
    summary = {("a", "x"): {"episodes": 3, "score": {"mean": 0.6}}, ("b", "x"): {"episodes": 1, "score": {"mean": 0.2}}}
    assert objective_value(summary, "score") == pytest.approx(0.5)
    success = _run(tmp_path / "success", 1)
    score = _run(tmp_path / "score", 2, objective="score")
    assert success.study_name != score.study_name
    for t in score.trials:
        scores = t.user_attrs["score"]
        assert t.value == pytest.approx(sum(scores.values()) / len(scores))  # one scenario, equal episodes
    doc = yaml.safe_load((tmp_path / "score" / "best.tuning.yaml").read_text())
    assert doc["tuning"]["objective_of"] == "score" and doc["tuning"]["objective"] == score.best_value
    with pytest.raises(TuneError, match="objective 'comfort'"):
        _run(tmp_path / "bad", 1, objective="comfort")


@pytest.mark.parametrize("path", sorted(p for p in TUNED_DIR.glob("*.yaml") if not p.name.endswith(TUNING_SUFFIX)),
                         ids=lambda p: p.stem)
def test_every_shipped_tuned_config_is_its_policys_and_drives(path):
    import numpy as np

    assert yaml.safe_load(tuning_path(path).read_text())["policy"] == path.stem  # configs/tuned/NAME.yaml is NAME's
    env = gym.make("bimp/EmergencyBrake-v0")
    policy = make_policy(path.stem, env)
    assert policy.config == make_policy(path.stem, env, config=path).config  # and its default
    obs, _ = env.reset(seed=3)
    policy.reset(seed=3)
    action = policy.act(obs)
    assert np.all(np.isfinite(action)) and env.action_space.contains(np.asarray(action, env.action_space.dtype))
