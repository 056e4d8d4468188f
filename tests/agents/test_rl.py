"""The SB3 baseline: its transforms, the shipped models as policies, and a short training run."""

from __future__ import annotations

import dataclasses
import json

import gymnasium as gym
import numpy as np
import pytest

from bimp import envs
from bimp.agents import rl, rl_train
from bimp.agents.commands import train_rl
from bimp.agents.policy import Policy
from bimp.agents.registry import make_policy
from bimp.configs import load_config
from bimp.envs.wrappers import features, n_features

from .interrupt import interrupted_run

SHIPPED = sorted(
    (algo, scenario) for algo in rl.ALGOS for scenario in envs.ENV_IDS
    if rl.model_name(algo, scenario).removesuffix(".zip") in rl.default_training_seeds()
)
EVAL_SEEDS = (7, 8, 9)


@pytest.fixture
def overtaking():
    env = gym.make(envs.env_id("overtaking"))
    yield env
    env.close()


def test_some_model_is_shipped_for_each_scenario():
    assert {scenario for _, scenario in SHIPPED} == set(envs.ENV_IDS)


def test_config_validates():
    assert rl.RLConfig().net_arch == (64, 64)
    with pytest.raises(ValueError, match="n_stepz"):
        load_config(rl.RLConfig, None, n_stepz=8)
    for bad in ({"algo": "dqn"}, {"scenario": "parking"}, {"timesteps": 0}, {"gamma": 1.5}, {"vec_env": "ray"},
                {"timesteps": 1.5}, {"net_arch": [64, "x"]}, {"ent_coef": True}, {"gamma": float("nan")}):
        key = next(iter(bad))
        with pytest.raises(ValueError, match=key):
            rl.RLConfig(**bad)


def test_factory_errors(overtaking, tmp_path, monkeypatch):
    with pytest.raises(TypeError, match="modle_path"):
        rl.make_ppo(overtaking, modle_path="x.zip")
    monkeypatch.setattr(rl, "MODEL_DIR", tmp_path)
    with pytest.raises(FileNotFoundError, match="no SAC model is shipped for overtaking"):
        rl.make_sac(overtaking)


def test_every_shipped_training_seed_loads_and_a_missing_one_is_named(overtaking):
    seeds = sorted(int(p.stem.rsplit("_s", 1)[1]) for p in rl.MODEL_DIR.glob("ppo_overtaking_s*.zip"))
    assert len(seeds) >= 3 and rl.default_training_seeds()["ppo_overtaking"] in seeds
    for seed in seeds:
        assert make_policy("ppo", overtaking, training_seed=seed).model_path.name == f"ppo_overtaking_s{seed}.zip"
    with pytest.raises(FileNotFoundError, match=r"training seed 99 \(shipped: \['ppo_overtaking_s"):
        make_policy("ppo", overtaking, training_seed=99)


@pytest.mark.parametrize(("algo", "scenario"), SHIPPED)
def test_shipped_model_acts_in_the_action_space(algo, scenario):
    env = gym.make(envs.env_id(scenario))
    policy = make_policy(algo, env)
    assert isinstance(policy, Policy)
    for seed in (0, 1):  # the scene changes at every reset: the policy must follow it
        obs, _ = env.reset(seed=seed)
        policy.reset(seed)
        for _ in range(20):
            action = policy.act(obs)
            assert action.dtype == np.float32 and env.action_space.contains(action)
            obs, *_ = env.step(action)
    env.close()


@pytest.mark.parametrize(("algo", "scenario"), SHIPPED[:1])
def test_policy_sees_what_training_saw(algo, scenario):
    """Policy.act on the raw env equals the model's prediction through the training wrapper."""
    raw, wrapped = gym.make(envs.env_id(scenario)), envs.PlanningWrapper(gym.make(envs.env_id(scenario)))
    policy = make_policy(algo, raw)
    for seed in (3, 4):
        obs, _ = raw.reset(seed=seed)
        feats, _ = wrapped.reset(seed=seed)
        for _ in range(30):
            x, _ = policy.model.predict(feats, deterministic=True)
            feats, *_ = wrapped.step(x)
            obs, *_ = raw.step(policy.act(obs))
            np.testing.assert_allclose(features(obs, raw.unwrapped.scene), feats, atol=1e-6)


@pytest.mark.parametrize(("algo", "scenario"), SHIPPED)
def test_shipped_model_beats_the_zero_action(algo, scenario):
    env = gym.make(envs.env_id(scenario))
    result = rl_train.compare_with_zero(env, make_policy(algo, env), EVAL_SEEDS)
    env.close()
    ours, zero = result["policy"], result["zero"]
    # Fewer failures than the zero action (which runs into OV1 on every seed), not none: the shipped default
    # collides on 2% of the results seeds (docs/rl.md), and three seeds are a smoke test, not a safety record.
    assert ours["collision"] + ours["offroad"] < zero["collision"] + zero["offroad"]
    if scenario == "overtaking":
        assert ours["progress"] > zero["progress"]
    else:
        # The zero action drives into the stopped traffic: stopping short of it is the goal here.
        assert ours["progress"] > 20.0


@pytest.mark.slow
@pytest.mark.parametrize("algo", rl.ALGOS)
def test_short_training_writes_a_loadable_model(algo, tmp_path):
    overrides = {"ppo": "n_steps: 64\n", "sac": "learning_starts: 64\n"}[algo] + "checkpoint_every: 128\n"
    (tmp_path / "overrides.yaml").write_text(overrides)
    out = tmp_path / algo
    code = train_rl.main(["--scenario", "emergency-brake", "--algo", algo, "--timesteps", "256", "--seed", "1",
                    "--config", str(tmp_path / "overrides.yaml"), "--out", str(out), "--eval-seeds", "1",
                    "--no-progress"])
    assert code == 0
    path = out / rl.model_name(algo, "emergency-brake")
    assert path.is_file() and (out / "curve.png").is_file()
    # one checkpoint, the last: a run folder small enough to commit
    assert [p.name for p in (out / "checkpoints").glob("*.zip")] == [f"{algo}_emergency-brake_256_steps.zip"]
    # the shipped model is lean: no optimizer moments, the checkpoint keeps them to resume from
    _, lean, _ = rl.read_model_file(path)
    _, full, _ = rl.read_model_file(next((out / "checkpoints").glob("*.zip")))
    optimizers = [name for name in full if name.endswith("optimizer")]
    assert optimizers and all(lean[n]["state"] == {} and full[n]["state"] for n in optimizers)
    assert path.stat().st_size < 0.6 * next((out / "checkpoints").glob("*.zip")).stat().st_size
    env = gym.make(envs.env_id("emergency-brake"))
    policy = getattr(rl, f"make_{algo}")(env, model=path)
    trusted = getattr(rl, f"make_{algo}")(env, model=path, trust_model=True)  # SB3's own load reads it too
    obs, _ = env.reset(seed=0)
    assert env.action_space.contains(policy.act(obs))
    np.testing.assert_array_equal(policy.act(obs), trusted.act(obs))


@pytest.mark.parametrize(("algo", "scenario"), SHIPPED[:1])
def test_sb3_evaluate_policy_refuses_the_raw_env_and_runs_on_the_wrapper(algo, scenario):
    """Raw observations and features have the same length: without the check SB3 would drive on nonsense."""
    from stable_baselines3.common.evaluation import evaluate_policy

    env = gym.make(envs.env_id(scenario))
    model = rl._algo_class(algo).load(rl._shipped_model(env, algo, None), device="cpu")
    with pytest.raises(ValueError, match="PlanningWrapper"):
        evaluate_policy(model, env, n_eval_episodes=1, warn=False)
    mean, _ = evaluate_policy(model, envs.PlanningWrapper(env), n_eval_episodes=1, warn=False)
    assert mean > 0  # a crash costs 20: it drove


def _untrained_model(scenario: str, tmp_path, meta: bool = True):
    """A PPO model on ``scenario``'s training wrapper, saved as `bimp train-rl` saves one (no training)."""
    from stable_baselines3.common.env_util import make_vec_env

    cfg = rl.RLConfig(scenario=scenario, n_steps=64)
    venv = make_vec_env(cfg.env_id, n_envs=1, seed=0, wrapper_class=envs.PlanningWrapper)
    model = rl_train.make_model(cfg, venv)
    if meta:
        model.bimp = {"scenario": scenario, "algo": "ppo", "n_features": venv.observation_space.shape[0]}
    path = tmp_path / f"{scenario}{'' if meta else '_bare'}.zip"
    model.save(path)
    venv.close()
    return path


def test_a_model_is_refused_on_another_scenario_and_without_its_record(tmp_path):
    path = _untrained_model("overtaking", tmp_path)
    brake = gym.make(envs.env_id("emergency-brake"))
    # the two scenarios' features have the same length: only the recorded scenario tells them apart
    assert n_features(brake.unwrapped.scene) == n_features(gym.make(envs.env_id("overtaking")).unwrapped.scene)
    with pytest.raises(ValueError, match="trained on overtaking, not emergency-brake"):
        make_policy("ppo", brake, model=path)
    with pytest.raises(ValueError, match="not written by `bimp train-rl`"):
        make_policy("ppo", brake, model=_untrained_model("emergency-brake", tmp_path, meta=False))
    assert isinstance(make_policy("ppo", gym.make(envs.env_id("overtaking")), model=path), Policy)


def test_a_model_drives_another_difficulty_of_its_family_only_when_asked(tmp_path):
    """cut-in's models are evaluated at `extreme` too (issue 50): one env class, features that mean the same."""
    path = _untrained_model("cut-in-hard", tmp_path)
    extreme = gym.make(envs.env_id("cut-in-extreme"))
    with pytest.raises(ValueError, match="trained on cut-in-hard, not cut-in-extreme.*trained_on=cut-in-hard"):
        make_policy("ppo", extreme, model=path)
    policy = make_policy("ppo", extreme, model=path, trained_on="cut-in-hard")
    assert policy.config["trained_on"] == "cut-in-hard"
    obs, _ = extreme.reset(seed=0)
    assert extreme.action_space.contains(policy.act(obs))
    with pytest.raises(ValueError, match="not cut-in-easy \\(trained_on\\)"):
        make_policy("ppo", extreme, model=path, trained_on="cut-in-easy")
    with pytest.raises(ValueError, match="a model of lane-drop-hard does not drive cut-in-extreme"):
        make_policy("ppo", extreme, model=path, trained_on="lane-drop-hard")
    with pytest.raises(ValueError, match="unknown scenario 'cut-in-hardest'"):
        make_policy("ppo", extreme, model=path, trained_on="cut-in-hardest")
    # a shipped model is looked up under the scenario it was trained on
    with pytest.raises(FileNotFoundError, match="no PPO model is shipped for cut-in-easy"):
        make_policy("ppo", extreme, trained_on="cut-in-easy", training_seed=9)
    # where only another difficulty of the family has models, the error says how to drive them
    with pytest.raises(FileNotFoundError, match="drive it with trained_on=emergency-brake-noisy-hard"):
        make_policy("ppo", gym.make(envs.env_id("emergency-brake-noisy")))


def _logged_steps(out) -> int:
    """Timesteps of the finished episodes in ``out``'s monitor logs."""
    from stable_baselines3.common.monitor import load_results

    return int(load_results(str(out))["l"].sum())


def test_training_resumes_from_its_last_checkpoint_and_refuses_another_run(tmp_path, monkeypatch):
    cfg = rl.RLConfig(scenario="emergency-brake", timesteps=1024, n_steps=64, checkpoint_every=256, seed=3)
    out = tmp_path / "run"
    interrupted_run(cfg, out, monkeypatch, after=300)
    # interrupted after the first checkpoint: no model where make_policy would look, one checkpoint to resume from
    path = out / cfg.model_name
    assert not path.exists() and list(out.glob("*.zip")) == [] and not (out / "train_time.json").exists()
    assert [p.name for p in (out / "checkpoints").iterdir()] == ["ppo_emergency-brake_256_steps.zip"]
    assert rl_train._latest_checkpoint(out)[0] == 256
    stray = out / "checkpoints" / "ppo_emergency-brake_replay_buffer_768_steps.npz.part"  # a crash's leftover
    stray.write_bytes(b"x")
    rl_train.train(dataclasses.replace(cfg, vec_env="subproc"), out, progress=False)  # how it runs may change
    assert not stray.exists() and [p.name for p in (out / "checkpoints").iterdir()] == [
        "ppo_emergency-brake_1024_steps.zip"]
    assert rl.read_model_file(path)[0]["num_timesteps"] == 1024  # 768 more, not 1024 again
    assert json.loads((out / "train_time.json").read_text())["resumed_at"] == 256
    assert json.loads((out / "segments.json").read_text()) == [0, 256]
    assert sorted(p.name for p in out.glob("*.monitor.csv")) == [f"{i}.monitor.csv" for i in range(4)]
    # the episodes the first segment played after its checkpoint are cut: every timestep is counted once
    assert _logged_steps(out) <= 1024
    with pytest.raises(ValueError, match="gamma: 0.99 there, 0.9 here"):
        rl_train.train(dataclasses.replace(cfg, gamma=0.9), out, progress=False)
    # a finished run made longer goes on from its last checkpoint; shorter is another run
    longer = dataclasses.replace(cfg, timesteps=1536)
    rl_train.train(longer, out, progress=False)
    assert rl.read_model_file(path)[0]["num_timesteps"] == 1536
    assert json.loads((out / "segments.json").read_text()) == [0, 256, 1024]
    assert json.loads((out / "config.json").read_text())["timesteps"] == 1536 and _logged_steps(out) <= 1536
    with pytest.raises(ValueError, match="timesteps: 1536 there, 1024 here"):
        rl_train.train(cfg, out, progress=False)


def test_a_resume_cuts_the_logs_back_to_its_checkpoint_keeping_their_lines_as_written(tmp_path):
    header = '#{"t_start": 1.0, "env_id": "x"}\nr,l,t\r\n'  # as SB3's Monitor writes them
    for i in (0, 1):  # one env's log each, in lockstep: 30 steps each at the checkpoint (60 over both)
        (tmp_path / f"{i}.monitor.csv").write_bytes((header + "1.5,10,0.1\r\n2.5,20,0.2\r\n3.5,10,0.3\r\n").encode())
    rl_train._drop_replayed_episodes(tmp_path, n_envs=2, segment_start=0, resume_at=60)
    for i in (0, 1):  # the third episode ended after step 30: cut; the others byte for byte
        assert (tmp_path / f"{i}.monitor.csv").read_bytes() == (header + "1.5,10,0.1\r\n2.5,20,0.2\r\n").encode()


def test_sac_resumes_without_its_replay_buffer_by_filling_a_new_one(tmp_path, monkeypatch):
    """A checkpoint from the repository has no buffer beside it (it is not committed): SAC keeps its nets and
    collects ``learning_starts`` random steps again before it learns, and says so."""
    cfg = rl.RLConfig(scenario="emergency-brake", algo="sac", timesteps=512, learning_starts=64,
                      checkpoint_every=256, seed=3)
    out = tmp_path / "run"
    interrupted_run(cfg, out, monkeypatch, after=300)
    checkpoint = rl_train._latest_checkpoint(out)[1]
    rl.buffer_path(checkpoint).unlink()
    resumed = {}
    real = rl_train._resume
    monkeypatch.setattr(rl_train, "_resume", lambda *a: resumed.setdefault("model", real(*a)))
    with pytest.warns(UserWarning, match="no replay buffer beside it: SAC resumes with an empty one, 64 steps"):
        path = rl_train.train(cfg, out, progress=False)
    model = resumed["model"]
    assert model.learning_starts == 256 + 64 and model.replay_buffer.pos == (512 - 256) // cfg.n_envs  # the new steps
    assert json.loads((out / "buffer_lost.json").read_text()) == [256]
    _, state_dicts, variables = rl.read_model_file(path)
    assert rl.read_model_file(path)[0]["num_timesteps"] == 512 and "log_ent_coef" in variables


def test_a_sac_warm_up_after_a_lost_buffer_lasts_past_a_later_resume(tmp_path, monkeypatch):
    cfg = rl.RLConfig(scenario="emergency-brake", algo="sac", timesteps=768, learning_starts=200,
                      checkpoint_every=128, seed=3)
    out = tmp_path / "run"
    interrupted_run(cfg, out, monkeypatch, after=300)  # checkpoint at 256
    rl.buffer_path(rl_train._latest_checkpoint(out)[1]).unlink()
    with pytest.warns(UserWarning, match="no replay buffer"):
        interrupted_run(cfg, out, monkeypatch, after=400)  # warm-up to 456; checkpoint at 384, with its buffer
    assert rl_train._latest_checkpoint(out)[0] == 384 and rl.buffer_path(rl_train._latest_checkpoint(out)[1]).is_file()
    resumed = {}
    real = rl_train._resume
    monkeypatch.setattr(rl_train, "_resume", lambda *a: resumed.setdefault("model", real(*a)))
    rl_train.train(cfg, out, progress=False)
    assert resumed["model"].learning_starts == 256 + 200  # not 200: it would learn from 128 new transitions
    # every segment's wall time, the interrupted ones too
    walls, cpus = (json.loads((out / name).read_text()) for name in ("wall.json", "cpu.json"))
    assert len(walls) == len(cpus) == len(json.loads((out / "segments.json").read_text())) == 3
    assert all(w > 0 for w in walls) and all(c > 0 for c in cpus[1:])


def test_a_run_without_checkpoints_is_not_made_longer_from_scratch(tmp_path):
    cfg = rl.RLConfig(scenario="emergency-brake", timesteps=256, n_steps=64, checkpoint_every=0, seed=3)
    rl_train.train(cfg, tmp_path / "run", progress=False)
    assert json.loads((tmp_path / "run" / "train_time.json").read_text())["timesteps"] == 256
    with pytest.raises(ValueError, match="finished run of 256 timesteps and no checkpoint to go on from"):
        rl_train.train(dataclasses.replace(cfg, timesteps=512), tmp_path / "run", progress=False)


def _fake_train(calls: list, fails: str = "never"):
    """A stand-in for :func:`rl_train.train`: writes what a finished run leaves, raises for scenario ``fails``."""
    def train(cfg, out, progress=True):
        calls.append((cfg.scenario, cfg.seed, out.name))
        if cfg.scenario == fails:
            raise RuntimeError("diverged")
        out.mkdir(parents=True, exist_ok=True)
        (out / "train_time.json").write_text('{"wall_s": 1.5}')
        return out / cfg.model_name
    return train


@pytest.mark.parametrize(("extra", "message"), [
    (["--out", "one"], "--out names one run's folder"),
    (["--seed", "1", "1"], "named twice"),
    (["--workers", "0"], "--workers must be >= 1"),
    (["--backend", "spark"], "unknown backend 'spark'"),
    (["--timesteps", "0"], "timesteps must be > 0"),
    (["--eval-seeds", "-1"], "--eval-seeds >= 0"),
    (["--runs-dir", "a", "--out", "b"], "give one"),
    (["--runs-dir", ""], "--runs-dir is empty"),  # not the current folder
    (["--scenario", "bimp/Overtaking-v0"], "['ppo_overtaking_s0'] named twice"),  # one scenario by two names
])
def test_a_grid_is_refused_before_any_run_trains(tmp_path, monkeypatch, capsys, extra, message):
    calls = []
    monkeypatch.setattr(rl_train, "train", _fake_train(calls))
    argv = ["--scenario", "emergency-brake", "overtaking", "--runs-dir", str(tmp_path), "--no-progress"]
    with pytest.raises(SystemExit) as exit_:
        train_rl.main(argv + extra)
    assert exit_.value.code == 2 and message in capsys.readouterr().err
    assert calls == []


def test_an_empty_out_is_refused_not_taken_for_the_current_folder(tmp_path, monkeypatch, capsys):
    calls = []
    monkeypatch.setattr(rl_train, "train", _fake_train(calls))
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_:
        train_rl.main(["--scenario", "overtaking", "--out", "", "--no-progress"])
    assert exit_.value.code == 2 and "--out is empty" in capsys.readouterr().err
    assert calls == [] and list(tmp_path.iterdir()) == []


def test_a_grid_refuses_a_folder_of_another_run_before_the_first_trains(tmp_path, monkeypatch, capsys):
    calls = []
    monkeypatch.setattr(rl_train, "train", _fake_train(calls))
    other = rl.RLConfig(scenario="overtaking", seed=2, timesteps=999_999)  # a longer run: not made shorter
    (tmp_path / rl_train.run_name(other)).mkdir()
    (tmp_path / rl_train.run_name(other) / "config.json").write_text(json.dumps(dataclasses.asdict(other)))
    with pytest.raises(SystemExit):  # the second scenario's second seed: after three runs that would have trained
        train_rl.main(["--scenario", "emergency-brake", "overtaking", "--seed", "1", "2", "--runs-dir", str(tmp_path)])
    assert "timesteps: 999999 there, 150000 here" in capsys.readouterr().err
    assert calls == []


def test_a_grid_trains_every_scenario_and_seed_and_a_failed_run_stops_no_other(tmp_path, monkeypatch, capsys):
    calls = []
    monkeypatch.setattr(rl_train, "train", _fake_train(calls, fails="overtaking"))
    code = train_rl.main(["--scenario", "overtaking", "emergency-brake", "--seed", "1", "2", "--runs-dir",
                          str(tmp_path), "--eval-seeds", "0", "--no-progress"])
    assert code == 1  # a failed run is not a success
    assert calls == [("overtaking", 1, "ppo_overtaking_s1"), ("overtaking", 2, "ppo_overtaking_s2"),
                     ("emergency-brake", 1, "ppo_emergency-brake_s1"), ("emergency-brake", 2, "ppo_emergency-brake_s2")]
    out = capsys.readouterr().out
    assert out.count("FAILED") == 2 and "RuntimeError: diverged" in out
    assert f"trained {tmp_path / 'ppo_emergency-brake_s2'}" in out and "2 of 4 runs failed" in out


def test_a_grid_of_real_runs_resumes_to_nothing(tmp_path, capsys):
    """Two short runs in this process; the same command again trains nothing (each folder holds its model)."""
    (tmp_path / "short.yaml").write_text("n_steps: 64\ncheckpoint_every: 0\n")
    argv = ["--scenario", "emergency-brake", "--seed", "1", "2", "--timesteps", "128", "--config",
            str(tmp_path / "short.yaml"), "--runs-dir", str(tmp_path), "--eval-seeds", "1", "--no-progress"]
    assert train_rl.main(argv) == 0
    first = {s: (tmp_path / f"ppo_emergency-brake_s{s}" / "train_time.json").read_text() for s in (1, 2)}
    assert capsys.readouterr().out.count("trained") == 2
    for s in (1, 2):
        model = tmp_path / f"ppo_emergency-brake_s{s}" / rl.model_name("ppo", "emergency-brake")
        assert rl.read_model_file(model)[0]["num_timesteps"] == 128
        assert (model.parent / "eval.json").is_file()
    assert train_rl.main(argv) == 0
    assert {s: (tmp_path / f"ppo_emergency-brake_s{s}" / "train_time.json").read_text() for s in (1, 2)} == first
    assert capsys.readouterr().out.count("trained earlier") == 2


@pytest.mark.slow
def test_a_grid_on_two_workers_trains_both_runs(tmp_path):
    (tmp_path / "short.yaml").write_text("n_steps: 64\ncheckpoint_every: 0\n")
    assert train_rl.main(["--scenario", "emergency-brake", "--seed", "1", "2", "--timesteps", "128", "--config",
                    str(tmp_path / "short.yaml"), "--runs-dir", str(tmp_path), "--workers", "2", "--eval-seeds",
                    "0", "--no-progress"]) == 0
    for s in (1, 2):
        model = tmp_path / f"ppo_emergency-brake_s{s}" / rl.model_name("ppo", "emergency-brake")
        assert rl.read_model_file(model)[0]["num_timesteps"] == 128


def test_one_run_trains_in_this_process_into_its_default_folder(tmp_path, monkeypatch, capsys):
    calls = []
    monkeypatch.setattr(rl_train, "train", _fake_train(calls))
    monkeypatch.chdir(tmp_path)
    (tmp_path / "seeded.yaml").write_text("seed: 7\n")  # a seed from the file, none on the command line
    assert train_rl.main(["--scenario", "overtaking", "--config", "seeded.yaml", "--eval-seeds", "0"]) == 0
    assert calls == [("overtaking", 7, "ppo_overtaking_s7")]
    assert (tmp_path / "runs/rl/ppo_overtaking_s7/train_time.json").is_file()
    assert "train wall time: 1.5 s" in capsys.readouterr().out
    monkeypatch.setattr(rl_train, "train", _fake_train(calls, fails="overtaking"))
    with pytest.raises(RuntimeError):  # not a refusal: a bug in training is a traceback, as before
        train_rl.main(["--scenario", "overtaking", "--eval-seeds", "0"])


def test_a_runs_dir_under_a_file_is_named_as_such(tmp_path, capsys):
    (tmp_path / "file").write_text("")
    with pytest.raises(SystemExit):
        train_rl.main(["--scenario", "overtaking", "--seed", "1", "2", "--runs-dir", str(tmp_path / "file" / "runs")])
    assert f"--runs-dir {tmp_path / 'file' / 'runs'} lies under" in capsys.readouterr().err


def test_ray_gets_absolute_run_folders_and_a_dead_worker_fails_the_command(tmp_path, monkeypatch, capsys):
    seen = {}

    def fake_run_groups(jobs, run, crashed, write, **options):
        seen.update(jobs=jobs, options=options)
        for job in jobs:
            for report in crashed(job, "the worker process running it died twice"):
                write(report)

    monkeypatch.setattr(train_rl, "start_backend", lambda *a: None)
    monkeypatch.setattr(train_rl, "run_groups", fake_run_groups)
    monkeypatch.chdir(tmp_path)
    code = train_rl.main(["--scenario", "overtaking", "--runs-dir", "rel", "--backend", "ray", "--address", "auto",
                    "--no-progress"])
    assert code == 1 and "WorkerDied: the worker process running it died twice" in capsys.readouterr().out
    assert [job[1] for job in seen["jobs"]] == [str(tmp_path / "rel" / "ppo_overtaking_s0")]
    assert seen["options"] == {"backend": "ray", "workers": 1, "address": "auto", "cpus": None}


def test_every_default_training_seed_names_a_shipped_model_that_loads_on_its_scenario():
    """defaults.json's keys are ``{algo}_{scenario}`` (a suite family's scenarios too, as paper-noisy's)."""
    for key, seed in rl.default_training_seeds().items():
        algo, scenario = key.split("_", 1)
        env = gym.make(envs.env_id(scenario))
        policy = make_policy(algo, env)
        assert policy.model_path.name == rl.shipped_name(algo, scenario, seed)
        obs, _ = env.reset(seed=0)
        assert env.action_space.contains(policy.act(obs))
        env.close()


def test_the_rl_config_files_load_and_sacs_is_the_default_run():
    from pathlib import Path

    folder = Path(rl.__file__).resolve().parents[1] / "configs" / "rl"
    loaded = {p.stem: load_config(rl.RLConfig, p) for p in sorted(folder.glob("*.yaml"))}
    assert {"ppo-sb3", "ppo-highway-env", "sac-sb3"} <= set(loaded)
    assert loaded["sac-sb3"] == rl.RLConfig(algo="sac")  # its runs are `bimp train-rl --algo sac`'s


def test_each_shipped_default_is_its_best_training_seed_on_the_tuning_seeds():
    """The rule of docs/rl.md, on the committed selection records (tuning seeds 100-149): the best training seed
    by success, then overtakes, then progress (`bimp aggregate` names it)."""
    from pathlib import Path

    from bimp.agents.evaluation.aggregate import aggregate, best_run
    from bimp.agents.evaluation.compare import label_results

    folder = Path(rl.__file__).resolve().parents[1] / "results" / "tuning" / "rl" / "selection"
    for key, seed in rl.default_training_seeds().items():
        algo, scenario = key.split("_", 1)
        seeds = sorted(int(p.stem.rsplit("_s", 1)[1]) for p in rl.MODEL_DIR.glob(f"{key}_s*.zip"))
        per_run = {f"{algo}-s{s}": {k: m for k, m in label_results(folder, f"{algo}-s{s}").items() if k[0] == scenario}
                   for s in seeds}
        assert len(seeds) == 3 and all(len(got) == 50 for got in per_run.values()), key
        assert best_run(aggregate(per_run), scenario) == f"{algo}-s{seed}", key
