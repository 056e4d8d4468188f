"""One config shape: every config file is a YAML of overrides, a tuned one's tuning beside it (NAME.tuning.yaml);
settings built in layers (``load_layered``); a renamed or moved key refused naming its new name; ``bimp migrate
FILE.yaml`` bringing an old file to today's shape with the values it had."""

import dataclasses
import json

import gymnasium as gym
import pytest
import yaml

from bimp import envs  # noqa: F401  (registers the envs)
from bimp.agents.cli import main
from bimp.agents.evaluation.provenance import resolved_config
from bimp.agents.files import write_atomic
from bimp.agents.registry import make_policy
from bimp.configs import ConfigError, is_old_tuned, load_layered, tuned_files, tuning_path


@dataclasses.dataclass(frozen=True)
class Inner:
    a: float = 1.0
    b: float = 2.0


@dataclasses.dataclass(frozen=True)
class Outer:
    n: int = 3
    inner: Inner = Inner()

    def __post_init__(self):
        if isinstance(self.inner, dict):
            object.__setattr__(self, "inner", Inner(**self.inner))


def test_layers_merge_nested_and_dotted_keys_in_order(tmp_path):
    (tmp_path / "f.yaml").write_text("inner: {a: 5.0}\n")
    cfg = load_layered(Outer, {"n": 4}, tmp_path / "f.yaml", None, {"inner.b": 7.0})
    assert cfg == Outer(n=4, inner=Inner(a=5.0, b=7.0))
    assert load_layered(Outer, {"inner": {"a": 9.0}}, base={"inner": {"b": 0.5}}).inner == Inner(9.0, 0.5)


@pytest.mark.parametrize("layer", [{"inner": {"old": 1.0}}, {"inner.old": 1.0}, {"inner": {"old": {"deep": 1}}}])
def test_a_moved_key_is_refused_naming_its_new_name_however_it_is_given(layer):
    with pytest.raises(ValueError, match=r"^inner\.old(\.deep)? is now inner\.b"):
        load_layered(Outer, layer, moved={"inner.old": "inner.b"})


def test_an_unknown_key_is_refused_naming_it():
    with pytest.raises(ValueError, match="nope"):
        load_layered(Outer, {"nope": 1})


@pytest.fixture(scope="module")
def env():
    return gym.make("bimp/EmergencyBrake-v0")


@pytest.mark.parametrize("overrides", [{"problem.barrier.brake_decel": 5.0},
                                       {"problem": {"barrier": {"brake_decel": 5.0}}}])
@pytest.mark.parametrize("policy", ["enkts", "mppi", "nmpc"])
def test_the_barriers_brake_decel_is_now_follower_decel(env, policy, overrides):
    with pytest.raises(ValueError, match=r"problem\.barrier\.brake_decel is now problem\.barrier\.follower_decel"):
        make_policy(policy, env, **overrides)
    assert make_policy(policy, env, **{"problem.barrier.follower_decel": 5.0}).config.problem.barrier.follower_decel \
        == 5.0
    with pytest.raises(ConfigError, match="follower_decel must be > 0"):
        make_policy(policy, env, **{"problem.barrier.follower_decel": 0.0})


def old_envelope(env, tmp_path, policy="enkts"):
    """A tuned config as ``bimp tune`` wrote it before the tuning moved beside it, the barrier's old key in it."""
    config = resolved_config(make_policy(policy, env, **{"problem.barrier.follower_decel": 4.5,
                                                          "problem.horizon": 25}))["config"]
    config["problem"]["barrier"]["brake_decel"] = config["problem"]["barrier"].pop("follower_decel")
    path = tmp_path / "best.yaml"
    doc = {"policy": policy, "tuning": {"study": "s", "trial": 3}, "config": json.loads(json.dumps(config))}
    path.write_text("# Written by `bimp tune`\n" + yaml.safe_dump(doc))
    return path


def test_an_old_tuned_file_is_refused_naming_the_command_then_migrated_to_the_same_config(env, tmp_path, capsys):
    path = old_envelope(env, tmp_path)
    assert is_old_tuned(yaml.safe_load(path.read_text()))
    with pytest.raises(ValueError, match=f"old shape .* `bimp migrate {path}`"):
        make_policy("enkts", env, config=path)
    assert main(["migrate", str(path)]) == 0
    assert "split" in capsys.readouterr().out
    config = yaml.safe_load(path.read_text())
    assert "policy" not in config and config["problem"]["barrier"]["follower_decel"] == 4.5
    assert yaml.safe_load(tuning_path(path).read_text()) == {"policy": "enkts", "tuning": {"study": "s", "trial": 3}}
    policy = make_policy("enkts", env, config=path)
    assert policy.config == make_policy("enkts", env, **{"problem.barrier.follower_decel": 4.5,
                                                         "problem.horizon": 25}).config
    with pytest.raises(ValueError, match="tuned for 'enkts', not 'enks'"):  # the tuning beside it says whose it is
        make_policy("enks", env, config=path)
    before = path.read_bytes()
    assert main(["migrate", str(path)]) == 0 and path.read_bytes() == before  # a second time: nothing to change
    assert "nothing to change" in capsys.readouterr().out


def test_a_plain_file_with_a_renamed_key_is_migrated_and_a_bad_file_reported(env, tmp_path, capsys):
    plain = tmp_path / "plain.yaml"
    plain.write_text("problem: {barrier: {brake_decel: 5.5}}\n")
    assert main(["migrate", str(plain), "--dry-run"]) == 0 and "brake_decel" in plain.read_text()
    assert main(["migrate", str(plain)]) == 0
    assert make_policy("enkts", env, config=plain).config.problem.barrier.follower_decel == 5.5
    bad = tmp_path / "list.yaml"
    bad.write_text("- 1\n")
    assert main(["migrate", str(bad)]) == 1 and "not a config" in capsys.readouterr().out


def test_a_shipped_tuned_config_under_the_new_shape_goes_under_a_file_of_overrides(env, tmp_path):
    # mppi ships a tuned config: a file of overrides goes on top of it, keeping the rest of its tuned problem.
    shipped = make_policy("mppi", env).config
    (tmp_path / "h.yaml").write_text("problem: {horizon: 30}\n")
    cfg = make_policy("mppi", env, config=tmp_path / "h.yaml").config
    assert cfg.problem.horizon == 30 and cfg.problem.sigma_barrier == shipped.problem.sigma_barrier
    assert dataclasses.replace(cfg, problem=dataclasses.replace(cfg.problem, horizon=shipped.problem.horizon)) \
        == shipped


def test_a_tuned_config_is_the_config_alone_and_its_tuning_beside_it(env, tmp_path):
    config = {"k_lat": 0.02}
    path = tmp_path / "lk.yaml"
    for file, text in tuned_files(path, config, "lane-keep", {"trial": 1}).items():
        write_atomic(file, text)
    assert yaml.safe_load(path.read_text()) == config
    assert yaml.safe_load((tmp_path / "lk.tuning.yaml").read_text())["policy"] == "lane-keep"
    assert make_policy("lane-keep", env, config=path).config.k_lat == 0.02
