"""bimp.agents.evaluation.provenance: a run is dirty when the code differs from its commit, not when its results folder
does."""

import dataclasses
import json
import subprocess
import sys

import pytest

from bimp.agents.evaluation import provenance
from bimp.agents.evaluation.provenance import config_hash, git_state, resolved_config
from bimp.agents.registry import PolicySpec, make_policy, register_policy
from bimp.configs import added_field


def test_a_changed_results_file_is_not_dirty_a_changed_code_file_is(tmp_path):
    git = lambda *a: subprocess.run(["git", *a], cwd=tmp_path, check=True, capture_output=True)  # noqa: E731
    git("init", "-q")
    (tmp_path / "planners").mkdir()
    (tmp_path / "results").mkdir()
    (tmp_path / "planners" / "core.py").write_text("x = 1\n")
    (tmp_path / "results" / "episodes.jsonl").write_text("{}\n")
    git("add", ".")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "start")
    commit, dirty = git_state(tmp_path)
    assert len(commit) == 40 and dirty is False
    (tmp_path / "results" / "episodes.jsonl").write_text("{}\n{}\n")  # a run appending to its tracked folder
    assert git_state(tmp_path) == (commit, False)
    (tmp_path / "planners" / "core.py").write_text("x = 2\n")
    assert git_state(tmp_path) == (commit, True)


def test_outside_a_checkout_there_is_no_state(tmp_path):
    assert git_state(tmp_path) == (None, None)


def test_a_package_inside_another_checkout_records_no_commit(tmp_path):
    """A wheel installed into a .venv inside some project's repository: that repository's commit is not ours."""
    subprocess.run(["git", "init", "-q"], cwd=tmp_path, check=True)
    subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "--allow-empty", "-m", "x"],
                   cwd=tmp_path, check=True)
    package = tmp_path / ".venv" / "lib" / "site-packages" / "bimp"
    package.mkdir(parents=True)
    assert git_state(tmp_path)[0] is not None and git_state(package) == (None, None)


@dataclasses.dataclass(frozen=True)
class Grown:
    """A toy policy's config: ``gain`` from the start; the test swaps this class to play later versions."""

    gain: float = 1.0


register_policy(PolicySpec(name="hash-toy", factory="tests.agents.toys:AlwaysBrake", label="toy", color="black",
                           config_class=f"{__name__}:Grown"))


def _version(monkeypatch, **fields):
    """``Grown`` with ``fields``: ``name: default`` or ``name: (default, neutral)`` for an added field."""
    spec = [(k, type(v[0]), added_field(*v[:1], neutral=v[1])) if isinstance(v, tuple)
            else (k, type(v), dataclasses.field(default=v)) for k, v in fields.items()]
    monkeypatch.setattr(sys.modules[__name__], "Grown", dataclasses.make_dataclass("Grown", spec, frozen=True))
    provenance._neutral.cache_clear()


def test_a_field_added_at_its_neutral_value_leaves_old_hashes_one_without_changes_them(monkeypatch):
    """Issue 28, item 2: a field added with the value that reproduces the old behaviour leaves the hash of a record
    made before it unchanged, so the record still resumes; a field no value of which reproduces the old behaviour
    (declared plain) changes the hash, so the old records are refused instead of taken for the new behaviour's."""
    old = {"config": {"gain": 1.0}, "scenario": {"x": 1}}
    _version(monkeypatch, gain=1.0)
    before = config_hash("hash-toy", old)
    _version(monkeypatch, gain=1.0, extra=(0, 0))
    assert config_hash("hash-toy", {"config": {"gain": 1.0, "extra": 0}, "scenario": {"x": 1}}) == before
    assert config_hash("hash-toy", {"config": {"gain": 1.0, "extra": 5}, "scenario": {"x": 1}}) != before
    _version(monkeypatch, gain=1.0, extra=(5, 0))  # new configs take 5; 0 still means "as before"
    assert config_hash("hash-toy", {"config": {"gain": 1.0, "extra": 0}, "scenario": {"x": 1}}) == before
    _version(monkeypatch, gain=1.0, extra=0)  # no neutral value: the old records are not the new behaviour's
    assert config_hash("hash-toy", {"config": {"gain": 1.0, "extra": 0}, "scenario": {"x": 1}}) != before
    provenance._neutral.cache_clear()


def test_a_value_whose_change_the_road_records_hashes_as_neutral_and_migrate_writes_the_neutral_one(monkeypatch):
    """``added_field(..., by_road=...)``: a value that reproduces the neutral one's behaviour except where the road
    says otherwise (and there the record's ``road`` says so) is left out of the hash; every other value is hashed;
    ``bimp migrate`` writes the neutral value itself into old records, never the list the hash compares with."""
    old = {"config": {"gain": 1.0}, "scenario": {"x": 1}}
    _version(monkeypatch, gain=1.0)
    before = config_hash("hash-toy", old)
    spec = [("gain", float, dataclasses.field(default=1.0)),
            ("guard", object, added_field(None, neutral=False, by_road=(None,)))]
    monkeypatch.setattr(sys.modules[__name__], "Grown", dataclasses.make_dataclass("Grown", spec, frozen=True))
    provenance._neutral.cache_clear()
    for value in (False, None):
        assert config_hash("hash-toy", {**old, "config": {"gain": 1.0, "guard": value}}) == before
    assert config_hash("hash-toy", {**old, "config": {"gain": 1.0, "guard": True}}) != before
    asked = {**old, "config": {"gain": 1.0, "guard": None}, "road": {"guard": True}}
    assert config_hash("hash-toy", asked) != before  # where the road asked, its record says so
    assert provenance.neutral_config("hash-toy") == {"guard": False}
    provenance._neutral.cache_clear()


def test_the_switches_added_for_the_claims_study_are_neutral_and_nmpc_slack_is_not():
    import gymnasium as gym

    env = gym.make("bimp/EmergencyBrake-v0")
    resolved = resolved_config(make_policy("enkts", env))
    before = {**resolved, "config": {k: v for k, v in resolved["config"].items()
                                     if k not in ("gate_barriers", "first_control_barriers", "update")}}
    assert config_hash("enkts", before) == config_hash("enkts", resolved)  # records made before the switches
    nmpc = resolved_config(make_policy("nmpc", env))
    hard = {**nmpc, "config": {k: v for k, v in nmpc["config"].items() if k != "slack_penalty"}}
    assert config_hash("nmpc", hard) != config_hash("nmpc", nmpc)  # the first wave's hard-constraint NMPC
    # a record holds infinities as null (JSON): the same hash
    enks = resolved_config(make_policy("enks", env))
    assert config_hash("enks", json.loads(json.dumps(provenance.plain(enks)))) == config_hash("enks", enks)


def test_planner_weights_are_hashed_by_content_not_by_path(tmp_path):
    """Issue 28, item 1: the same weights at two paths are one config; new weights at the same path another (a
    retrained planners/weights/mlp.pt must not adopt the records of the old one)."""
    import gymnasium as gym

    from bimp.planners.dynamics import WEIGHTS_PATH

    env = gym.make("bimp/EmergencyBrake-v0")
    copies = [tmp_path / "a" / "w.pt", tmp_path / "b" / "c" / "w.pt"]
    for copy in copies:
        copy.parent.mkdir(parents=True)
        copy.write_bytes(WEIGHTS_PATH.read_bytes())

    def hash_with(dynamics: str) -> str:
        return config_hash("enkts", resolved_config(make_policy("enkts", env, **{"problem.dynamics": dynamics})))

    assert hash_with("mlp") == hash_with(str(copies[0])) == hash_with(str(copies[1]))
    policy = make_policy("enkts", env, **{"problem.dynamics": str(copies[1])})
    assert policy.artifacts == {"problem.dynamics": str(copies[1])}
    assert make_policy("enkts", env).artifacts == {"problem.dynamics": "bimp:planners/weights/mlp.pt"}
    before = hash_with(str(copies[0]))
    import torch

    weights = torch.load(copies[0], weights_only=True)
    weights["state_dict"] = {k: v + 1e-3 for k, v in weights["state_dict"].items()}  # retrained, same file name
    torch.save(weights, copies[0])
    assert hash_with(str(copies[0])) != before
    assert hash_with("bicycle") != hash_with("mlp") and "files" not in resolved_config(
        make_policy("enkts", env, **{"problem.dynamics": "bicycle"}))


@pytest.mark.parametrize("policy", ["enkts", "enks", "mppi"])  # NMPC plans on the paper's roads only
def test_what_a_curved_road_changes_in_a_planner_is_recorded_and_hashed(policy):
    """A planner on a road whose steering bound is not the paper's plans with the problem as the road changes it
    (problem.for_road: scaled steering noise, the course tracked). Its resolved config says so under ``"road"``, so
    that records made before the road changed anything are another config, never resumed as these; on the paper's
    scenarios there is no ``"road"`` and the hash is what it was."""
    import gymnasium as gym

    from bimp.planners.problem import road_changes

    def resolved(env_id):
        env = gym.make(env_id)
        env.reset(seed=0)
        return resolved_config(make_policy(policy, env))

    paper, uturn = resolved("bimp/EmergencyBrake-v0"), resolved("bimp/u-turn-v0")
    assert "road" not in paper and uturn["road"]["track_course"] is True
    guard = {"road_guard": True} if policy != "mppi" else {}  # the road asks EnKTS and EnKS for the guard
    assert uturn["road"] == json.loads(json.dumps({**road_changes(make_policy(policy, gym.make(
        "bimp/u-turn-v0")).config.problem, 0.3), **guard}))
    assert config_hash(policy, uturn) != config_hash(policy, {k: v for k, v in uturn.items() if k != "road"})
