"""Model files, checkpoints and replay buffers load without unpickling anything (issue 24, docs/security.md).

Each crafted file carries a pickle whose ``__reduce__`` creates a marker file when unpickled: no marker, no code
ran. With ``trust_model=True`` SB3's own load runs, and the marker appears: the crafted files are real."""

from __future__ import annotations

import base64
import dataclasses
import json
import pickle
import zipfile
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

from bimp import envs
from bimp.agents import rl, rl_train
from bimp.agents.cli import main as bimp
from bimp.agents.commands import train_rl
from bimp.agents.evaluation.records import read_arms, read_records, record_config
from bimp.agents.registry import make_policy

from .interrupt import interrupted_run

SHIPPED = sorted(rl.MODEL_DIR.glob("*.zip"))


class Marker:
    """Unpickled, it creates the file ``path``: the stand-in for any code a crafted file could run."""

    def __init__(self, path: Path):
        self.path = path

    def __reduce__(self):
        return Path.touch, (self.path,)


def _rewrite(src: Path, dst: Path, **entries: bytes) -> Path:
    """A copy of the zip ``src`` at ``dst`` with ``entries`` (name -> bytes) replaced or added."""
    with zipfile.ZipFile(src) as old, zipfile.ZipFile(dst, "w") as new:
        for item in old.infolist():
            if item.filename not in entries:
                new.writestr(item, old.read(item.filename))
        for name, content in entries.items():
            new.writestr(name, content)
    return dst


def _evil_data(src: Path, marker: Path, **plain) -> bytes:
    """``src``'s data entry with an extra ``:serialized:`` pickle of :class:`Marker` (as SB3 writes one), and
    ``plain`` entries replaced."""
    with zipfile.ZipFile(src) as archive:
        data = json.loads(archive.read("data"))
    data["extra"] = {":type:": "<class 'object'>",
                     ":serialized:": base64.b64encode(pickle.dumps(Marker(marker))).decode()}
    data.update(plain)
    return json.dumps(data).encode()


def _scenario(path: Path) -> str:
    return path.stem.split("_", 1)[1].rsplit("_s", 1)[0]


@pytest.fixture
def overtaking():
    env = gym.make(envs.env_id("overtaking"))
    yield env
    env.close()


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.stem)
def test_shipped_models_act_as_sb3_loads_them(path):
    """The safe loader's actions are SB3 load's, bit for bit, on a drive and on random features."""
    algo = path.stem.split("_")[0]
    env = gym.make(envs.env_id(_scenario(path)))
    safe = make_policy(algo, env, model=path)
    trusted = make_policy(algo, env, model=path, trust_model=True)  # our own file: its pickles are ours
    assert safe.model.observation_space == trusted.model.observation_space
    assert safe.model.action_space == trusted.model.action_space
    obs, _ = env.reset(seed=5)
    for _ in range(15):
        action = safe.act(obs)
        np.testing.assert_array_equal(action, trusted.act(obs))
        obs, *_ = env.step(action)
    box = safe.model.observation_space
    x = np.random.default_rng(0).uniform(box.low, box.high, size=(32, *box.shape)).astype(np.float32)
    np.testing.assert_array_equal(safe.model.predict(x, deterministic=True)[0],
                                  trusted.model.predict(x, deterministic=True)[0])
    # The file by its content, never by where it lies (issue 28); shipped, it is named relative to the package.
    # The switch is recorded when on.
    assert sorted(safe.config) == ["algo", "model_sha256"]
    assert safe.artifacts == {"model": f"bimp:agents/models/{path.name}"}
    assert trusted.config == {**safe.config, "trust_model": True}
    env.close()


def test_a_crafted_model_runs_no_code_through_the_api(overtaking, tmp_path):
    shipped = rl._shipped_model(overtaking, "ppo", None)
    marker = tmp_path / "marker"
    evil = _rewrite(shipped, tmp_path / "evil.zip", data=_evil_data(shipped, marker))
    policy = make_policy("ppo", overtaking, model=evil)  # the pickled entry is dropped unread
    assert not marker.exists()
    obs, _ = overtaking.reset(seed=0)
    assert overtaking.action_space.contains(policy.act(obs))
    make_policy("ppo", overtaking, model=evil, trust_model=True)  # SB3's load: the file is really crafted
    assert marker.exists()


def test_a_crafted_model_runs_no_code_through_the_cli(tmp_path):
    shipped = rl.MODEL_DIR / rl.shipped_name("ppo", "overtaking", rl.default_training_seeds()["ppo_overtaking"])
    marker = tmp_path / "marker"
    evil = _rewrite(shipped, tmp_path / "evil.zip", data=_evil_data(shipped, marker))
    code = bimp(["evaluate", "--scenario", "overtaking", "--policy", "ppo", "--set", f"ppo.model={evil}",
                 "--seeds", "0", "--workers", "1", "--traces", "0", "--out", str(tmp_path / "eval")])
    assert code == 0 and not marker.exists()
    (record,) = read_records(tmp_path / "eval")
    config = record_config(record, read_arms(tmp_path / "eval"))
    assert record["status"] == "ok" and "trust_model" not in config["config"]
    code = bimp(["evaluate", "--scenario", "overtaking", "--policy", "ppo", "--set", f"ppo.model={evil}",
                 "ppo.trust_model=true", "--seeds", "0", "--workers", "1", "--out", str(tmp_path / "trusted")])
    assert code == 0 and marker.exists()  # the switch reaches SB3's load, and is recorded
    (record,) = read_records(tmp_path / "trusted")
    assert record_config(record, read_arms(tmp_path / "trusted"))["config"]["trust_model"] is True


def test_a_crafted_weights_entry_is_refused_naming_the_file(overtaking, tmp_path):
    """``policy.pth`` as a plain pickle: ``weights_only`` refuses it; the error names the file and the way out."""
    shipped = rl._shipped_model(overtaking, "ppo", None)
    marker = tmp_path / "marker"
    evil = _rewrite(shipped, tmp_path / "evil.zip", **{"policy.pth": pickle.dumps(Marker(marker), protocol=2)})
    with pytest.raises(ValueError, match=rf"{evil} is not a model file .*weights_only=True.*train-rl.*trust_model"):
        make_policy("ppo", overtaking, model=evil)
    assert not marker.exists()
    code = bimp(["evaluate", "--scenario", "overtaking", "--policy", "ppo", "--set", f"ppo.model={evil}",
                 "--seeds", "0", "--workers", "1", "--out", str(tmp_path / "eval")])
    assert code == 2 and not marker.exists() and not (tmp_path / "eval" / "episodes.jsonl").exists()


def test_every_torch_load_on_the_safe_path_is_weights_only(overtaking, monkeypatch):
    """Whatever SB3 is installed (up to 2.7 its zip reader passed ``weights_only=False``): the safe path calls
    ``torch.load`` itself, and only with ``weights_only=True``."""
    import torch

    real, calls = torch.load, []

    def guarded(*args, **kwargs):
        calls.append(kwargs.get("weights_only"))
        assert kwargs.get("weights_only") is True, "torch.load without weights_only=True on the safe path"
        return real(*args, **kwargs)

    monkeypatch.setattr(torch, "load", guarded)
    from stable_baselines3.common import save_util

    def sb3_reader(*args, **kwargs):  # its weights_only depends on the SB3 version installed: never on this path
        raise AssertionError("the safe path called SB3's load_from_zip_file")

    monkeypatch.setattr(save_util, "load_from_zip_file", sb3_reader)
    for algo in ("ppo", "sac"):
        rl.read_model_file(rl._shipped_model(overtaking, algo, None))
        make_policy(algo, overtaking)
    assert calls and all(calls)


def test_files_that_do_not_fit_are_refused_naming_the_file_and_why(overtaking, tmp_path):
    shipped = rl._shipped_model(overtaking, "ppo", None)
    not_zip = tmp_path / "model.zip"
    not_zip.write_bytes(pickle.dumps(Marker(tmp_path / "marker")))
    with pytest.raises(ValueError, match=rf"{not_zip} is not a model file .*BadZipFile.*bimp train-rl"):
        make_policy("ppo", overtaking, model=not_zip)
    narrow = _rewrite(shipped, tmp_path / "narrow.zip",
                      data=_evil_data(shipped, tmp_path / "marker", policy_kwargs={"net_arch": [32, 32]}))
    with pytest.raises(ValueError, match=rf"{narrow} does not fit a PPO policy .*size mismatch"):
        make_policy("ppo", overtaking, model=narrow)
    bare = _rewrite(shipped, tmp_path / "bare.zip", data=_evil_data(shipped, tmp_path / "marker", bimp=None))
    with pytest.raises(ValueError, match="not written by `bimp train-rl`"):
        make_policy("ppo", overtaking, model=bare)
    sac = rl.MODEL_DIR / rl.shipped_name("sac", "overtaking", 1)
    with pytest.raises(ValueError, match="is a SAC model, not PPO"):
        make_policy("ppo", overtaking, model=sac)
    with pytest.raises(ValueError, match="trust_model must be true or false"):
        make_policy("ppo", overtaking, model=shipped, trust_model="yes")
    assert not (tmp_path / "marker").exists()


def _sac_run(tmp_path, monkeypatch) -> tuple[rl.RLConfig, Path]:
    """A short SAC run interrupted after its first checkpoint."""
    cfg = rl.RLConfig(scenario="emergency-brake", algo="sac", timesteps=192, learning_starts=32, batch_size=16,
                      buffer_size=400, checkpoint_every=96, seed=2)
    out = tmp_path / "run"
    interrupted_run(cfg, out, monkeypatch, after=100)
    return cfg, out


def test_resume_reads_the_checkpoint_as_sb3_load_does_and_runs_no_code(tmp_path, monkeypatch):
    from stable_baselines3 import SAC
    from stable_baselines3.common.env_util import make_vec_env

    cfg, out = _sac_run(tmp_path, monkeypatch)
    checkpoint = rl_train._latest_checkpoint(out)[1]
    buffer = rl.buffer_path(checkpoint)
    assert buffer.is_file() and not list(out.glob("checkpoints/*.pkl"))  # no pickle is written

    # the checkpoint's state, read the safe way, is what SB3's load (of our own file) restores
    venv = make_vec_env(cfg.env_id, n_envs=cfg.n_envs, seed=0, wrapper_class=envs.PlanningWrapper)
    ours, theirs = rl_train._resume(cfg, venv, checkpoint), SAC.load(checkpoint, env=venv, device="cpu")
    assert ours.num_timesteps == theirs.num_timesteps == 96 and ours._n_updates == theirs._n_updates
    for name, state in theirs.get_parameters().items():
        mine = ours.get_parameters()[name]
        if name == "policy":
            for key in state:
                np.testing.assert_array_equal(mine[key].numpy(), state[key].numpy())
        else:
            assert repr(mine) == repr(state)  # optimizer states: step counts and moments
    assert ours.log_ent_coef.item() == theirs.log_ent_coef.item()
    # SB3 checkpoints before it stores the step's transition: 47 of the 48 steps per env are in the buffer
    rows = ours.replay_buffer.pos
    assert rows == 96 // cfg.n_envs - 1 and np.all(ours.replay_buffer.observations[:rows].any(axis=-1))
    venv.close()

    # a crafted checkpoint and a pickled buffer where an older bimp wrote one: resume runs no code
    marker = tmp_path / "marker"
    _rewrite(checkpoint, tmp_path / "evil.zip", data=_evil_data(checkpoint, marker)).replace(checkpoint)
    buffer.with_suffix(".pkl").write_bytes(pickle.dumps(Marker(marker)))
    rl_train.train(cfg, out, progress=False)
    assert not marker.exists()
    assert rl.read_model_file(out / cfg.model_name)[0]["num_timesteps"] == 192


def test_a_crafted_or_missing_replay_buffer_is_refused_and_runs_no_code(tmp_path, capsys, monkeypatch):
    cfg, out = _sac_run(tmp_path, monkeypatch)
    buffer = rl.buffer_path(rl_train._latest_checkpoint(out)[1])
    marker = tmp_path / "marker"
    # an array of objects: np.save pickles it, np.load(allow_pickle=False) refuses it before unpickling
    with np.load(buffer) as saved:
        arrays = dict(saved)
    np.savez(buffer, **{**arrays, "observations": np.array([Marker(marker)], dtype=object)})
    with pytest.raises(ValueError, match=rf"{buffer} is not a replay buffer of this run.*allow_pickle"):
        rl_train.train(cfg, out, progress=False)
    assert not marker.exists()
    # through the command: one line, exit 2
    overrides = tmp_path / "overrides.yaml"
    overrides.write_text(json.dumps({k: v for k, v in dataclasses.asdict(cfg).items()
                                     if k not in ("scenario", "algo", "net_arch")}))
    with pytest.raises(SystemExit) as exit_:
        train_rl.main(["--scenario", "emergency-brake", "--algo", "sac", "--config", str(overrides), "--out", str(out),
                 "--no-progress"])
    assert exit_.value.code == 2 and "is not a replay buffer of this run" in capsys.readouterr().err
    assert not marker.exists()
    # only an older bimp's pickle: refused, naming it, and not read
    buffer.unlink()
    buffer.with_suffix(".pkl").write_bytes(pickle.dumps(Marker(marker)))
    with pytest.raises(ValueError, match=r"replay_buffer_96_steps.pkl is a pickled one .*not read"):
        rl_train.train(cfg, out, progress=False)
    assert not marker.exists()
    # a buffer of another run's size is refused, naming the array
    np.savez(buffer, **{**arrays, "observations": arrays["observations"][:, :1]})
    with pytest.raises(ValueError, match=r"observations has shape \(47, 1, 21\), this run's buffer \(47, 2, 21\)"):
        rl_train.train(cfg, out, progress=False)


def test_a_model_is_identified_by_its_content_not_where_it_lies(overtaking, tmp_path):
    """Issue 28: a config (and its hash) holds no path; a user's file is named as given, apart from the config."""
    from bimp.agents.evaluation.provenance import config_hash, resolved_config

    shipped = rl._shipped_model(overtaking, "ppo", None)
    here, there = tmp_path / "a" / "m.zip", tmp_path / "b" / "c" / "m.zip"
    for copy in (here, there):
        copy.parent.mkdir(parents=True)
        copy.write_bytes(shipped.read_bytes())
    policies = [make_policy("ppo", overtaking, model=m) for m in (shipped, here, str(there))]
    assert len({config_hash("ppo", resolved_config(p)) for p in policies}) == 1
    assert [p.artifacts["model"] for p in policies] == [f"bimp:agents/models/{shipped.name}", str(here), str(there)]
    assert str(tmp_path) not in json.dumps(resolved_config(policies[1]))
