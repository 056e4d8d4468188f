"""bimp.agents.provenance: a run is dirty when the code differs from its commit, not when its results folder does."""

import dataclasses
import json
import subprocess
import sys

from bimp.agents import provenance
from bimp.agents.provenance import config_hash, git_state, resolved_config
from bimp.agents.registry import PolicySpec, make_policy, register_policy


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
    """A toy policy's config: ``gain`` from the start, ``extra`` added later with a default that keeps the old
    behaviour (the test swaps this class's fields to play each version)."""

    gain: float = 1.0


register_policy(PolicySpec(name="hash-toy", factory="tests.agents.toys:AlwaysBrake", label="toy", color="black",
                           config_class=f"{__name__}:Grown"))


def _version(monkeypatch, **fields):
    version = dataclasses.make_dataclass("Grown", [(k, type(v), dataclasses.field(default=v)) for k, v in
                                                   fields.items()], frozen=True)
    monkeypatch.setattr(sys.modules[__name__], "Grown", version)
    provenance._class_defaults.cache_clear()


def test_config_growth_leaves_old_hashes_and_a_changed_default_does_not(monkeypatch):
    """Issue 28, item 2: a field added with a default leaves the hash of a record made before it unchanged, so the
    record still resumes; a changed default changes what an old record's config hashes to, so it is refused."""
    _version(monkeypatch, gain=1.0)
    before = config_hash("hash-toy", {"config": {"gain": 1.0}, "scenario": {"x": 1}})
    _version(monkeypatch, gain=1.0, extra=0)
    assert config_hash("hash-toy", {"config": {"gain": 1.0, "extra": 0}, "scenario": {"x": 1}}) == before
    assert config_hash("hash-toy", {"config": {"gain": 1.0, "extra": 5}, "scenario": {"x": 1}}) != before
    _version(monkeypatch, gain=2.0, extra=0)  # the default moved: a record made at the old default is not the new
    assert config_hash("hash-toy", {"config": {"gain": 1.0}, "scenario": {"x": 1}}) != before
    provenance._class_defaults.cache_clear()


def test_the_shipped_planners_hash_without_their_defaults_and_as_their_records_hold_them():
    import gymnasium as gym

    env = gym.make("bimp/EmergencyBrake-v0")
    for name in ("enkts", "enks", "nmpc"):
        resolved = resolved_config(make_policy(name, env))
        assert provenance.class_defaults(name) is not None
        # fields at their class default (the switches added later among them) do not enter the hash
        dropped = {k: v for k, v in resolved["config"].items() if v != provenance.class_defaults(name).get(k)}
        assert config_hash(name, {"config": dropped}) == config_hash(name, resolved)
        # a record holds infinities as null (JSON): the same hash
        assert config_hash(name, json.loads(json.dumps(provenance.plain(resolved)))) == config_hash(name, resolved)
