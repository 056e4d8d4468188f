"""Training the reinforcement-learning baseline (``bimp train-rl``): stable-baselines3 PPO or SAC on a bimp env.

Training (``bimp train-rl``)::

    bimp train-rl --scenario overtaking --algo ppo --timesteps 150000 --seed 0 --vec-env subproc

writes ``{algo}_{scenario}.zip`` (the final model), ``checkpoints/``, ``*.monitor.csv``, ``curve.png`` (episode
return vs timesteps), ``config.json`` and ``eval.json`` (a quick check against the zero action) to ``--out``
(default ``runs/rl/{algo}_{scenario}_s{seed}``); a rerun into the same folder resumes from the latest
checkpoint. Copy the model to ``agents/models/{algo}_{scenario}_s{seed}.zip`` to ship it; the shipped ones and
how they were made: ``docs/rl.md``.

Several runs at once, the grid of ``--scenario`` x ``--seed``, each in ``--runs-dir`` (default ``runs/rl``) under
its default name, on a pool of ``--workers`` processes or a Ray cluster (the backends of ``bimp evaluate``)::

    bimp train-rl --scenario cut-in-hard stalled-vehicle-hard --seed 1 2 3 --workers 2
    bimp train-rl --scenario cut-in-hard stalled-vehicle-hard --seed 1 2 3 --backend ray --address HEAD:6379

Every run's settings and folder are checked before the first trains; a run that fails is reported and the others
go on; the same command again resumes each unfinished run from its checkpoints and trains no finished one again.
Ray's workers write the runs' folders: on several machines ``--runs-dir`` must be a disk every node mounts.

The policy that acts with a trained model, its config and the safe reading of model files:
:mod:`bimp.agents.rl`.
"""


from __future__ import annotations

import io
import json
import time
import warnings
import zipfile
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from bimp.agents.baselines import ZeroAction
from bimp.agents.errors import EvaluationError
from bimp.agents.files import read_json, read_json_or, write_atomic
from bimp.agents.rl import (
    PPOFeaturePolicy,
    RLConfig,
    SACFeaturePolicy,
    SB3Policy,
    buffer_path,
    error_brief,
    load_buffer,
    read_model_file,
    save_buffer,
    shipped_name,
)
from bimp.agents.rl_curves import last_episode_time, monitor_files, per_segment, plot_curve, seconds, trained
from bimp.agents.rollout import rollout
from bimp.configs import load_config
from bimp.envs.wrappers import PlanningWrapper

_EARLIER = "delete it to resume from an earlier checkpoint (or train into a new --out)"


def _resume(cfg: RLConfig, venv, checkpoint: Path):
    """The model of ``cfg`` on ``venv`` in the state of ``checkpoint`` (:func:`_checkpoint_callback`'s zip), read
    without unpickling: a fresh :func:`make_model`, then the checkpoint's state dicts (policy and optimizers),
    variables (SAC's ``log_ent_coef``) and counters. What SB3's ``load`` restores beyond that is logging
    (the recent episodes' returns) or settings ``cfg`` gives anyway. SAC: its replay buffer, :func:`load_buffer`,
    or without one :func:`_refill_buffer`."""
    import torch
    from stable_baselines3.common.save_util import recursive_getattr

    data, state_dicts, variables = read_model_file(checkpoint, how=_EARLIER)
    model = make_model(cfg, venv)
    names, variable_names = model._get_torch_save_params()
    if set(state_dicts) != set(names) or set(variables) != set(variable_names):
        raise ValueError(f"{checkpoint} holds {sorted(state_dicts)} and {sorted(variables)}, not the "
                         f"{cfg.algo.upper()} state {names} and {variable_names}; {_EARLIER}")
    try:
        model.set_parameters(state_dicts, exact_match=True, device="cpu")
        with torch.no_grad():
            for name in variable_names:  # in place: the entropy optimizer holds this very tensor
                recursive_getattr(model, name).copy_(variables[name])
        for counter in ("num_timesteps", "_n_updates", "_episode_num"):
            setattr(model, counter, int(data[counter]))
        if cfg.algo == "sac":  # a warm-up after a resume without buffer (_refill_buffer) lasts past later resumes
            model.learning_starts = max(cfg.learning_starts, int(data.get("learning_starts", 0)))
    except (ValueError, KeyError, RuntimeError, TypeError) as err:
        raise ValueError(f"{checkpoint} does not fit this run ({error_brief(err)}); {_EARLIER}") from None
    if cfg.algo == "sac":
        buffer = buffer_path(checkpoint)
        if buffer.is_file() or buffer.with_suffix(".pkl").is_file():  # load_buffer refuses a pickled one
            load_buffer(model.replay_buffer, buffer)
        else:
            _refill_buffer(model, cfg, checkpoint)
    return model


def _refill_buffer(model: Any, cfg: RLConfig, checkpoint: Path) -> None:
    """SAC resumed from a checkpoint without its replay buffer (a repository holds the checkpoints, not their
    buffers of up to ``buffer_size`` transitions): it keeps its nets, target nets, optimizers and entropy
    coefficient, and starts again from an empty buffer as a fresh run does, ``learning_starts`` steps of random
    actions before its next update, so that it never fits its critics to a few transitions. What it loses is the
    past experience: its next updates see only the new steps. Said in a warning and recorded in
    ``buffer_lost.json`` (the timesteps of each such resume) beside the run."""
    warnings.warn(f"{checkpoint.name} has no replay buffer beside it: SAC resumes with an empty one, "
                  f"{cfg.learning_starts} steps of random actions before it learns again", stacklevel=3)
    model.learning_starts = model.num_timesteps + cfg.learning_starts
    lost = checkpoint.parent.parent / "buffer_lost.json"
    record = read_json_or(lost, [])
    write_atomic(lost, json.dumps([*record, model.num_timesteps]) + "\n")


def model_bytes(model: Any, lean: bool = False) -> bytes:
    """SB3's zip of ``model`` (``model.save``), in memory so that it reaches disk in one step
    (:func:`bimp.agents.files.write_atomic`); ``lean``: through :func:`lean_zip`."""
    buffer = io.BytesIO()
    model.save(buffer)
    return lean_zip(buffer.getvalue()) if lean else buffer.getvalue()


def lean_zip(model_zip: bytes) -> bytes:
    """An SB3 model zip with each optimizer's state emptied: Adam's two moments per weight, which acting never
    reads (two thirds of the file). The weights, the optimizers' settings and the data entry stay, so SB3's own
    ``load`` still reads the file (with fresh optimizers). Read with ``weights_only``: nothing is unpickled."""
    import torch

    lean = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(model_zip)) as full, zipfile.ZipFile(lean, "w", zipfile.ZIP_DEFLATED) as out:
        for name in full.namelist():
            entry = full.read(name)
            if name.endswith("optimizer.pth"):  # policy.optimizer, actor./critic.optimizer, ent_coef_optimizer
                state = torch.load(io.BytesIO(entry), map_location="cpu", weights_only=True)
                emptied = io.BytesIO()
                torch.save({**state, "state": {}}, emptied)
                entry = emptied.getvalue()
            out.writestr(name, entry)
    return lean.getvalue()


def _checkpoint_callback(cfg: RLConfig, out: Path, clock: Callable[[], None] = lambda: None):
    """Every ``cfg.checkpoint_every`` timesteps, the model to ``out/checkpoints/{name}_{steps}_steps.zip`` (SAC's
    replay buffer beside it first, by :func:`save_buffer`, no pickle: a checkpoint on disk always has its buffer),
    each file written whole or not at all, then every other file there removed (older checkpoints, a buffer whose
    checkpoint a crash never wrote): a run folder holds one, small enough to commit with the run (the buffer is
    not). ``clock`` is called at each checkpoint (the run's wall time, :func:`train`)."""
    from stable_baselines3.common.callbacks import BaseCallback

    folder, prefix, every = out / "checkpoints", cfg.model_name.removesuffix(".zip"), cfg.checkpoint_every

    class Checkpoints(BaseCallback):
        def _on_training_start(self) -> None:
            self.passed = self.num_timesteps // every  # a resumed run counts from its checkpoint

        def _on_step(self) -> bool:
            if self.num_timesteps // every == self.passed:
                return True
            self.passed = self.num_timesteps // every
            folder.mkdir(parents=True, exist_ok=True)
            path = folder / f"{prefix}_{self.num_timesteps}_steps.zip"
            if getattr(self.model, "replay_buffer", None) is not None:
                save_buffer(self.model.replay_buffer, buffer_path(path))
            write_atomic(path, model_bytes(self.model))
            for old in folder.iterdir():
                if old not in (path, buffer_path(path)):
                    old.unlink()
            clock()
            return True

    return Checkpoints()


# --- training ------------------------------------------------------------------------------------------
def _progress_callback(total: int):
    """A tqdm bar over timesteps with the mean return of the last episodes (SB3's own bar needs ``rich``)."""
    from stable_baselines3.common.callbacks import BaseCallback
    from tqdm import tqdm

    class TqdmCallback(BaseCallback):
        def _on_training_start(self) -> None:
            self.bar = tqdm(total=total, unit="step", dynamic_ncols=True)
            self.done = 0

        def _on_step(self) -> bool:
            # PPO rounds the total up to whole rollouts: keep the bar at its total.
            now = min(self.num_timesteps, total)
            self.bar.update(now - self.done)
            self.done = now
            episodes = self.model.ep_info_buffer
            if episodes and self.n_calls % 50 == 0:
                self.bar.set_postfix(ep_return=f"{np.mean([e['r'] for e in episodes]):.1f}", refresh=False)
            return True

        def _on_training_end(self) -> None:
            self.bar.close()

    return TqdmCallback()


def make_model(cfg: RLConfig, venv: Any) -> Any:
    """The SB3 model of ``cfg`` on the vectorized, wrapped envs ``venv``."""
    common = dict(learning_rate=cfg.learning_rate, gamma=cfg.gamma, seed=cfg.seed, device="cpu", verbose=0,
                  policy_kwargs=dict(net_arch=list(cfg.net_arch)))
    if cfg.algo == "ppo":
        from stable_baselines3 import PPO

        return PPO(PPOFeaturePolicy, venv, n_steps=cfg.n_steps, batch_size=cfg.batch_size or 64,
                   n_epochs=cfg.n_epochs, gae_lambda=cfg.gae_lambda, ent_coef=cfg.ent_coef, **common)
    from stable_baselines3 import SAC

    return SAC(SACFeaturePolicy, venv, buffer_size=cfg.buffer_size, learning_starts=cfg.learning_starts,
               batch_size=cfg.batch_size or 256, tau=cfg.tau, **common)


def _latest_checkpoint(out: Path) -> tuple[int, Path | None]:
    """``(timesteps, path)`` of the checkpoint with the most timesteps in ``out/checkpoints``
    (``{name}_{steps}_steps.zip``); ``(0, None)`` when there is none."""
    found = sorted((int(p.stem.split("_")[-2]), p) for p in (out / "checkpoints").glob("*_steps.zip"))
    return found[-1] if found else (0, None)


# Settings that change how a run is computed, not what it computes: a resume may change them.
_RESUMABLE_CHANGES = ("vec_env", "checkpoint_every")


def check_same_run(cfg: RLConfig, out: Path) -> None:
    """Refuse to write into ``out`` when it holds another configuration's run: results never mix. The same run
    with more ``timesteps`` is not another: it continues from its last checkpoint."""
    path = out / "config.json"
    if not path.is_file():
        return
    before = read_json(path)
    if not isinstance(before, dict):
        raise EvaluationError(f"{path} is not a training run's config (not a JSON object): train into a new --out")
    now = json.loads(json.dumps(asdict(cfg)))  # tuples as lists, as they were written
    differ = sorted(k for k in set(before) | set(now)
                    if before.get(k) != now.get(k) and k not in _RESUMABLE_CHANGES)
    # Longer is a resume: the learning rates are constant, so a run to 300k from its 150k checkpoint is the
    # 300k run (as reproducible as any resume). Shorter would keep steps the config says were not trained.
    if differ == ["timesteps"] and isinstance(before["timesteps"], int) and before["timesteps"] < cfg.timesteps:
        return
    if differ:
        changes = ", ".join(f"{k}: {before.get(k)!r} there, {now.get(k)!r} here" for k in differ)
        raise ValueError(f"{out} holds a run with other settings ({changes}); choose another folder")


def _drop_replayed_episodes(out: Path, n_envs: int, segment_start: int, resume_at: int) -> None:
    """Cut the interrupted segment's monitor logs back to the checkpoint a run resumes from: the steps after it
    are played again by the resumed run, and would otherwise count twice in the curve. The envs step in lockstep,
    so at the checkpoint each env had played ``(resume_at - segment_start) / n_envs`` of the segment's steps."""
    budget = (resume_at - segment_start) / n_envs
    for log in monitor_files(out)[-n_envs:]:
        lines = log.read_bytes().splitlines(keepends=True)  # bytes: the lines kept stay as written (\r\n, \n)
        kept, steps = lines[:2], 0  # the JSON header and the column names (r,l,t)
        for row in lines[2:]:
            steps += int(row.split(b",")[1])
            if steps > budget:
                break
            kept.append(row)
        write_atomic(log, b"".join(kept))


def train(cfg: RLConfig, out: Path, progress: bool = True) -> Path:
    """Train ``cfg``, writing the model, checkpoints, monitor logs, ``curve.png`` and ``config.json`` to
    ``out``. Returns the model's path.

    Resumes: when ``out`` holds checkpoints of the same config, training continues from the latest one for the
    remaining timesteps. The interrupted segment's monitor logs are cut back to that checkpoint (its later
    episodes are played again), the new segment's logs take the next file numbers, so the curve counts every
    timestep once, and the algorithm and envs are reseeded from ``seed`` and the checkpoint's timesteps. SAC's
    checkpoints have its replay buffer beside them (``.npz``). Nothing is unpickled (:func:`_resume`). When the
    final model is there, nothing is trained. A resumed run is reproducible for a given checkpoint, not identical
    to an uninterrupted one. ``out`` holding another config's run is an error naming the settings that differ."""
    import torch
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    path = out / cfg.model_name
    check_same_run(cfg, out)
    if _finished(cfg, out):
        return path
    # The nets are tiny: more threads only fight the env processes (and other users) for the cores.
    torch.set_num_threads(1)
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / "config.json", json.dumps(asdict(cfg), indent=2) + "\n")
    segments_file = out / "segments.json"  # the timesteps each segment (run, or resume) started from
    segments = read_json_or(segments_file, [0])
    if not (isinstance(segments, list) and segments and all(type(n) is int and n >= 0 for n in segments)):
        raise EvaluationError(f"{segments_file} is not a list of step counts: train into a new --out")
    resume_at, checkpoint = _latest_checkpoint(out)
    if checkpoint is None and trained(out) is not None:
        raise ValueError(f"{out} holds a finished run of {trained(out)} timesteps and no checkpoint to go on from "
                         f"(checkpoint_every 0?): train the longer run into a new --out")
    walls, cpus = _walls(out, "wall.json", len(segments)), _walls(out, "cpu.json", len(segments))
    if monitor_files(out):
        # the interrupted segment ran at least until its last logged episode, whose rows the cut below drops
        walls[-1] = max(walls[-1], last_episode_time(out, cfg.n_envs))
        _drop_replayed_episodes(out, cfg.n_envs, segments[-1], resume_at)
        segments.append(resume_at)
        walls.append(0.0)
        cpus.append(0.0)
    write_atomic(segments_file, json.dumps(segments) + "\n")
    write_atomic(out / "wall.json", json.dumps(walls) + "\n")
    segment = len(monitor_files(out)) // cfg.n_envs
    venv = make_vec_env(cfg.env_id, n_envs=cfg.n_envs, seed=cfg.seed, start_index=segment * cfg.n_envs,
                        monitor_dir=str(out), wrapper_class=PlanningWrapper,
                        vec_env_cls=SubprocVecEnv if cfg.vec_env == "subproc" else DummyVecEnv)
    if checkpoint is None:
        model = make_model(cfg, venv)
    else:
        try:
            model = _resume(cfg, venv, checkpoint)  # reads it without unpickling
        except ValueError:
            venv.close()  # subproc envs are processes
            raise
        model.set_random_seed(cfg.seed + model.num_timesteps)  # the algorithm's draws and the envs' seeds
    # Saved with the model as plain JSON in its data entry: a model is refused on another scenario's env, whose
    # features may have the same length and mean other things.
    model.bimp = {"scenario": cfg.scenario, "algo": cfg.algo, "n_features": venv.observation_space.shape[0]}
    done = model.num_timesteps
    start = time.perf_counter()

    cpu_start = time.process_time()

    def clock() -> None:  # this segment's wall and CPU time so far, kept at each checkpoint and at the end
        walls[-1], cpus[-1] = round(time.perf_counter() - start, 1), round(time.process_time() - cpu_start, 1)
        write_atomic(out / "wall.json", json.dumps(walls) + "\n")
        write_atomic(out / "cpu.json", json.dumps(cpus) + "\n")

    callbacks = [_checkpoint_callback(cfg, out, clock)] if cfg.checkpoint_every else []
    if progress:
        callbacks.append(_progress_callback(cfg.timesteps))
    model.learn(total_timesteps=max(cfg.timesteps - done, 0), callback=callbacks, reset_num_timesteps=done == 0)
    venv.close()
    clock()
    write_atomic(path, model_bytes(model, lean=True))  # never half a model where make_policy looks
    # what was trained: PPO rounds up to whole rollouts (150,528 for 150k at 1,024 steps a rollout)
    write_atomic(out / "train_time.json", json.dumps({"wall_s": walls[-1], "timesteps": int(model.num_timesteps),
                                                      "resumed_at": done or None}) + "\n")
    plot_curve(out, out / "curve.png", title=f"{cfg.algo.upper()} {cfg.scenario} (seed {cfg.seed})")
    return path


def _walls(out: Path, name: str, n_segments: int) -> list[float]:
    """``wall.json`` or ``cpu.json``: the wall or CPU seconds of each segment so far (the training process's CPU
    time: with more runs than cores side by side, wall time counts the waiting too), one per entry of
    ``segments.json`` (zeros for the segments of a run older than the file)."""
    return per_segment(seconds(out, name) or [], n_segments)


def _finished(cfg: RLConfig, out: Path) -> bool:
    """Whether ``out`` holds ``cfg``'s finished run: its model and ``train_time.json``, written last, for at least
    as many timesteps as ``cfg`` asks (fewer: the run is being made longer)."""
    return (out / cfg.model_name).is_file() and (trained(out) or 0) >= cfg.timesteps


def wall_s(out: Path) -> float:
    """The training wall time [s] a finished run recorded."""
    wall = read_json(out / "train_time.json")
    if not (isinstance(wall, dict) and isinstance(wall.get("wall_s"), (int, float))):
        raise EvaluationError(f"{out / 'train_time.json'} holds no wall_s")
    return float(wall["wall_s"])


def quick_check(env: gym.Env, policy, seed: int) -> dict[str, float]:
    """One episode of :func:`bimp.agents.rollout.rollout`: ``progress`` (m along the road), ``collision``, ``offroad``,
    ``return`` and ``steps``. A quick check for training and tests, not the full evaluation."""
    episode = rollout(env, policy, seed)
    t = episode.trace
    return {"progress": t["s"][-1] - t["s"][0], "collision": float(any(t["collision"])),
            "offroad": float(any(t["offroad"])), "return": episode.total_reward, "steps": episode.steps}


def compare_with_zero(env: gym.Env, policy, seeds) -> dict[str, dict[str, float]]:
    """Means over ``seeds`` of :func:`quick_check` for ``policy`` and for :class:`ZeroAction`."""
    result = {}
    for name, pol in (("policy", policy), ("zero", ZeroAction(env))):
        runs = [quick_check(env, pol, seed) for seed in seeds]
        result[name] = {k: float(np.mean([r[k] for r in runs])) for k in runs[0]}
    return result


def check_model(cfg: RLConfig, path: Path, out: Path, seeds: int) -> dict[str, dict[str, float]]:
    """:func:`compare_with_zero` of the model ``path`` on ``seeds`` training seeds (100 on), written to
    ``out/eval.json``: a quick check that training learned something, not an evaluation."""
    env = gym.make(cfg.env_id)
    result = compare_with_zero(env, SB3Policy(env, path, cfg.algo), range(100, 100 + seeds))
    env.close()
    write_atomic(out / "eval.json", json.dumps(result, indent=2) + "\n")
    return result


def run_name(cfg: RLConfig) -> str:
    """A run's default folder name, ``{algo}_{scenario}_s{seed}``: the name its model ships under, less ``.zip``."""
    return shipped_name(cfg.algo, cfg.scenario, cfg.seed).removesuffix(".zip")


def train_job(job: tuple[dict[str, Any], str, int]) -> list[dict[str, Any]]:
    """One run of a grid, ``(RLConfig values, out, check seeds)``, in a backend's worker: :func:`train` (resuming
    from ``out``) and :func:`check_model`. Its report in a one-item list (a backend's records): the model, the
    training wall time, whether it was trained by an earlier command, and the check; or the error that stopped it."""
    values, out, seeds = job
    try:
        cfg = load_config(RLConfig, None, **values)
        finished = _finished(cfg, Path(out))
        path = train(cfg, Path(out), progress=False)
        report: dict[str, Any] = {"run": out, "model": str(path), "earlier": finished, "wall_s": wall_s(Path(out))}
        if seeds:
            report["check"] = check_model(cfg, path, Path(out), seeds)
    except Exception as err:  # noqa: BLE001 -- one run's failure is its report: hours of the others go on
        return [{"run": out, "error": f"{type(err).__name__}: {err}"}]
    return [report]


def job_crashed(job: tuple[dict[str, Any], str, int], why: str) -> list[dict[str, Any]]:
    return [{"run": job[1], "error": f"WorkerDied: {why}"}]


def report_line(report: dict[str, Any]) -> str:
    """One line of a run's report as ``bimp train-rl`` prints it."""
    if "error" in report:
        return f"FAILED {report['run']}: {report['error']}"
    done = "trained earlier" if report.get("earlier") else "trained"
    line = f"{done} {report['run']}: {report['model']}, {report['wall_s']} s"
    if "check" in report:
        mine, zero = report["check"]["policy"], report["check"]["zero"]
        line += (f"; progress {mine['progress']:.1f} m (zero action {zero['progress']:.1f} m), "
                 f"collisions {mine['collision']:.2f}")
    return line
