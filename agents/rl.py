"""Reinforcement-learning baseline: stable-baselines3 PPO or SAC, acting through the :class:`Policy` protocol.

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

Inference: ``make_policy("ppo", env)`` loads the default training seed's model of the env's scenario
(``agents/models/{algo}_{scenario}_s{seed}.zip``, the default in ``agents/models/defaults.json``), the scenario
taken from ``env.spec.id``; ``training_seed=S`` picks another shipped seed, ``model=PATH`` any file. A model
records the scenario it was trained on and is refused on another's env. Over training seeds: ``bimp aggregate``.

Model files, checkpoints and replay buffers are read without unpickling (:func:`read_model_file`), so a file
from anywhere runs no code; ``trust_model=True`` falls back to SB3's own ``load``, which does unpickle
(docs/security.md).

Observation and action go through fixed transforms, the same at training (:class:`bimp.envs.PlanningWrapper`) and
at inference (:class:`SB3Policy`): ego-relative scaled features and actions on the planning bounds, rate-limited
(:mod:`bimp.envs.wrappers` says why).

The env's reward is used as it is: it pays tracking of the reference speed *along the road* and of the
reference lane, so weaving or spinning earns less than driving straight; stopping earns only the lane term
(0.4 of 1 per step), less than driving at the reference speed, and a crash costs 20 and ends the episode.
Its speed term is 0.5 v_ref wide: at 0.2 v_ref, following a slower OV earned about what stopping earns and the
overtaking model learned to stop behind OV1. One of the three shipped overtaking seeds still does (docs/rl.md).
"""

from __future__ import annotations

import argparse
import io
import json
import pickle
import time
import zipfile
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, Callable, NoReturn

import gymnasium as gym
import numpy as np
from stable_baselines3.common.policies import ActorCriticPolicy, BasePolicy
from stable_baselines3.sac.policies import SACPolicy

from bimp import envs
from bimp.agents.backends import BackendError, check_backend, run_groups, start_backend
from bimp.agents.baselines import ZeroAction
from bimp.agents.cli import EvaluationError, add_backend_arguments, check_out_dir
from bimp.agents.records import read_json, write_atomic, write_figure
from bimp.agents.rollout import rollout
from bimp.configs import check_fields, file_sha256, read_yaml
from bimp.envs.wrappers import PlanningWrapper, features, n_features, to_env_action

MODEL_DIR = Path(__file__).resolve().parent / "models"
ALGOS = ("ppo", "sac")


# --- configuration -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RLConfig:
    """One training run. ``batch_size=None`` takes the algorithm's usual value (PPO 64, SAC 256);
    ``n_steps``, ``n_epochs``, ``ent_coef`` and ``gae_lambda`` are PPO's, ``buffer_size``, ``learning_starts``
    and ``tau`` SAC's. ``vec_env``: ``"dummy"`` steps the envs in this process (one core), ``"subproc"`` one
    process each. ``checkpoint_every``: timesteps between checkpoints (0: none)."""

    scenario: str = "overtaking"
    algo: str = "ppo"
    timesteps: int = 150_000
    seed: int = 0
    n_envs: int = 2
    vec_env: str = "dummy"
    net_arch: tuple[int, ...] = (64, 64)
    learning_rate: float = 3e-4
    gamma: float = 0.99
    batch_size: int | None = None
    n_steps: int = 512
    n_epochs: int = 10
    gae_lambda: float = 0.95
    ent_coef: float = 0.0
    buffer_size: int = 200_000
    learning_starts: int = 2_000
    tau: float = 0.005
    checkpoint_every: int = 25_000

    def __post_init__(self) -> None:
        check_fields(self)  # types and lengths, errors naming the key
        envs.env_id(self.scenario)  # raises ValueError naming the choices
        if self.algo not in ALGOS:
            raise ValueError(f"algo must be one of {ALGOS}, got {self.algo!r}")
        if self.vec_env not in ("dummy", "subproc"):
            raise ValueError(f"vec_env must be 'dummy' or 'subproc', got {self.vec_env!r}")
        positive = {"timesteps": self.timesteps, "n_envs": self.n_envs, "n_steps": self.n_steps,
                    "n_epochs": self.n_epochs, "buffer_size": self.buffer_size,
                    "learning_rate": self.learning_rate, "tau": self.tau}
        for key, value in positive.items():
            if not value > 0:
                raise ValueError(f"{key} must be > 0, got {value}")
        if self.batch_size is not None and self.batch_size < 2:
            raise ValueError(f"batch_size must be >= 2, got {self.batch_size}")
        if not self.net_arch or min(self.net_arch) < 1:
            raise ValueError(f"net_arch must be a non-empty list of positive widths, got {self.net_arch}")
        if not (0.0 < self.gamma <= 1.0 and 0.0 <= self.gae_lambda <= 1.0):
            raise ValueError("gamma must lie in (0, 1] and gae_lambda in [0, 1]")
        if self.ent_coef < 0 or self.learning_starts < 0 or self.checkpoint_every < 0:
            raise ValueError("ent_coef, learning_starts and checkpoint_every must be >= 0")

    @classmethod
    def from_mapping(cls, values: dict[str, Any]) -> RLConfig:
        """Build from a mapping (YAML overrides); an unknown key raises ``ValueError`` naming it."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"unknown RLConfig key(s) {unknown}; known keys are {sorted(known)}")
        return cls(**values)

    @property
    def env_id(self) -> str:
        return envs.env_id(self.scenario)

    @property
    def model_name(self) -> str:
        return model_name(self.algo, self.scenario)


def model_name(algo: str, scenario: str) -> str:
    """File name of a model: ``{algo}_{scenario}.zip`` with the scenario's short name."""
    short = envs.scenario_name(scenario) or scenario
    return f"{algo}_{short}.zip"


def _algo_class(algo: str):
    from stable_baselines3 import PPO, SAC

    return {"ppo": PPO, "sac": SAC}[algo]


class _FeaturesOnly:
    """Mixin for an SB3 policy that acts on :func:`bimp.envs.wrappers.features`: refuses any other input.

    The raw observation and the features have the same length here, so SB3's own shape check passes and a
    model handed the raw env (``evaluate_policy(model, gym.make(...))``) would silently drive on nonsense.
    Features lie inside the observation box; a raw observation never does (positions and speeds are far
    outside +-5), so the box tells them apart."""

    def obs_to_tensor(self, observation):
        box = self.observation_space
        x = np.asarray(observation, dtype=np.float32)
        if x.shape[-1:] == box.shape and not np.all((x >= box.low - 1e-5) & (x <= box.high + 1e-5)):
            raise ValueError(
                "this bimp model acts on the planning features, not the raw observation: evaluate it on "
                "bimp.envs.PlanningWrapper(gym.make(...)) (SB3's evaluate_policy), or use "
                "bimp.make_policy('ppo', env), which applies the features itself")
        return super().obs_to_tensor(observation)


class PPOFeaturePolicy(_FeaturesOnly, ActorCriticPolicy):
    """PPO's MLP policy on the planning features (refuses raw observations)."""


class SACFeaturePolicy(_FeaturesOnly, SACPolicy):
    """SAC's MLP policy on the planning features (refuses raw observations)."""


FEATURE_POLICIES = {"ppo": PPOFeaturePolicy, "sac": SACFeaturePolicy}


# --- model files, read without unpickling --------------------------------------------------------------
# An SB3 zip holds a JSON ``data`` entry (attributes that are not plain JSON are cloudpickled into it, base64 under
# ``:serialized:``) and ``.pth`` state dicts. SB3's ``load`` unpickles every ``:serialized:`` entry, so a crafted
# file runs any code. Everything bimp needs is plain: the ``bimp`` record, ``policy_kwargs`` and the counters are
# plain JSON, the weights are tensors (read with ``weights_only=True``), and the spaces are bimp's own
# (:class:`PlanningWrapper`'s). docs/security.md.
_HOW = ("retrain it with `bimp train-rl`, or, only if you trust its source, pass trust_model=True "
        "(`--set ppo.trust_model=true`, or sac.), which loads it with SB3's own load: that unpickles it, and a "
        "crafted file then runs any code")


def _brief(err: Exception) -> str:
    """``err`` on one line, cut at 200 characters (torch's and numpy's messages run over several lines)."""
    return f"{type(err).__name__}: {' '.join(str(err).split())[:200]}"


def read_model_file(path: str | Path, how: str = _HOW) -> tuple[dict[str, Any], dict[str, dict], dict[str, Any]]:
    """``(data, state_dicts, variables)`` of an SB3 zip without unpickling anything: ``data`` its plain-JSON
    attributes (the pickled ``:serialized:`` ones are dropped unread), ``state_dicts`` ``{"policy": ...,
    "policy.optimizer": ...}`` (one per ``.pth`` entry) and ``variables`` ``pytorch_variables.pth`` (SAC's
    ``log_ent_coef``; ``{}`` when absent), both read by ``torch.load(weights_only=True)``.
    ``ValueError`` naming the file when it is not such a zip, and ending in ``how`` (what to do instead)."""
    import torch

    try:
        with zipfile.ZipFile(path) as archive:
            data = json.loads(archive.read("data"))
            state_dicts, variables = {}, {}
            for name in archive.namelist():
                if not name.endswith(".pth"):
                    continue
                # Read here, not by SB3's load_from_zip_file: SB3 up to 2.7 passes weights_only=False there, which
                # unpickles. SB3 names each entry after its attribute; pytorch_variables holds SAC's log_ent_coef.
                loaded = torch.load(io.BytesIO(archive.read(name)), map_location="cpu", weights_only=True)
                if name == "pytorch_variables.pth":
                    variables = loaded
                else:
                    state_dicts[name.removesuffix(".pth")] = loaded
    except FileNotFoundError:
        raise
    except pickle.UnpicklingError:
        raise ValueError(f"{path} is not a model file bimp can read without unpickling (a .pth entry holds more "
                         f"than weights: torch.load(weights_only=True) refused it); {how}") from None
    except Exception as err:  # any other failure to parse an untrusted file: not a zip, no JSON data
        raise ValueError(f"{path} is not a model file bimp can read without unpickling "
                         f"({_brief(err)}); {how}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: its data entry is not a JSON object; {how}")
    plain = {k: v for k, v in data.items() if not (isinstance(v, dict) and ":serialized:" in v)}
    return plain, state_dicts, variables or {}


def _check_record(path: Path, meta: Any, algo: str, env: gym.Env) -> None:
    """Refuse a model whose ``bimp`` record (written by :func:`train`) is missing or names another algorithm,
    scenario or feature count than ``env``'s."""
    if not isinstance(meta, dict) or not {"scenario", "algo", "n_features"} <= set(meta):
        raise ValueError(f"{path} was not written by `bimp train-rl` (it records no scenario); retrain it")
    if meta["algo"] != algo:
        raise ValueError(f"{path} is a {str(meta['algo']).upper()} model, not {algo.upper()}")
    scenario = _scenario_of(env)
    if scenario is not None and meta["scenario"] != scenario:
        raise ValueError(f"{path} was trained on {meta['scenario']}, not {scenario}: its features mean other "
                         f"things there")
    n = n_features(env.unwrapped.scene)
    if meta["n_features"] != n:
        raise ValueError(f"{path} expects {meta['n_features']} features; this feature set gives {n}")


def _load_safe(path: Path, algo: str, env: gym.Env) -> BasePolicy:
    """The deterministic SB3 policy of the model file ``path`` rebuilt from plain data, nothing unpickled:
    ``FEATURE_POLICIES[algo]`` on ``env``'s :class:`PlanningWrapper` spaces (features ``(n,)``, action ``(2,)``
    in [-1, 1]), the file's ``policy_kwargs`` (``net_arch``) and its ``policy`` state dict, loaded strict."""
    data, state_dicts, _ = read_model_file(path)
    _check_record(path, data.get("bimp"), algo, env)
    kwargs = data.get("policy_kwargs")
    if not isinstance(kwargs, dict) or "net_arch" not in kwargs:
        raise ValueError(f"{path} records no plain policy_kwargs with net_arch; {_HOW}")
    spaces = PlanningWrapper(env)
    try:
        # Only JSON values reach the constructor: a class given by name is a string here, and refused.
        policy = FEATURE_POLICIES[algo](spaces.observation_space, spaces.action_space, lambda _: 0.0,
                                        **{"use_sde": bool(data.get("use_sde", False)), **kwargs})
        policy.load_state_dict(state_dicts["policy"], strict=True)
    except (TypeError, ValueError, KeyError, RuntimeError) as err:
        raise ValueError(f"{path} does not fit a {algo.upper()} policy on {spaces.observation_space.shape} "
                         f"features ({_brief(err)}); {_HOW}") from None
    policy.set_training_mode(False)
    return policy


def _load_trusted(path: Path, algo: str, env: gym.Env) -> BasePolicy:
    """The policy of ``path`` by SB3's own ``load``, which unpickles the file: whatever code it holds runs.
    Only behind ``trust_model=True``."""
    # Schedules are pickled closures; replacing them keeps loading independent of the training Python.
    custom = {"learning_rate": 0.0, "lr_schedule": lambda _: 0.0, "clip_range": lambda _: 0.0}
    model = _algo_class(algo).load(path, device="cpu", custom_objects=custom)
    _check_record(path, getattr(model, "bimp", None), algo, env)
    if model.observation_space.shape != (n_features(env.unwrapped.scene),) or model.action_space.shape != (2,):
        raise ValueError(f"{path} expects observations {model.observation_space.shape} and actions "
                         f"{model.action_space.shape}; this feature set gives "
                         f"({n_features(env.unwrapped.scene)},) and (2,)")
    return model.policy


_EARLIER = "delete it to resume from an earlier checkpoint (or train into a new --out)"


def _resume(cfg: RLConfig, venv, checkpoint: Path):
    """The model of ``cfg`` on ``venv`` in the state of ``checkpoint`` (a ``CheckpointCallback`` zip), read
    without unpickling: a fresh :func:`make_model`, then the checkpoint's state dicts (policy and optimizers),
    variables (SAC's ``log_ent_coef``) and counters. What SB3's ``load`` restores beyond that is logging
    (the recent episodes' returns) or settings ``cfg`` gives anyway. SAC: its replay buffer, :func:`load_buffer`."""
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
    except (ValueError, KeyError, RuntimeError, TypeError) as err:
        raise ValueError(f"{checkpoint} does not fit this run ({_brief(err)}); {_EARLIER}") from None
    if cfg.algo == "sac":
        load_buffer(model.replay_buffer, _buffer_path(checkpoint))  # without it SAC learns from an empty buffer
    return model


# SB3's ReplayBuffer arrays, each (buffer_size // n_envs, n_envs, ...); next_observations is None when
# optimize_memory_usage.
_BUFFER_ARRAYS = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")


def _buffer_path(checkpoint: Path) -> Path:
    """``{name}_replay_buffer_{steps}_steps.npz`` beside the checkpoint ``{name}_{steps}_steps.zip``."""
    name, steps = checkpoint.name.removesuffix("_steps.zip").rsplit("_", 1)
    return checkpoint.with_name(f"{name}_replay_buffer_{steps}_steps.npz")


def save_buffer(buffer, path: Path) -> None:
    """Write SB3's ``ReplayBuffer`` as ``.npz`` of plain arrays (its filled rows) with ``pos`` and ``full``, in
    place of SB3's pickle; written whole or not at all (a temporary file, then renamed)."""
    rows = buffer.buffer_size if buffer.full else buffer.pos
    arrays = {k: getattr(buffer, k)[:rows] for k in _BUFFER_ARRAYS if getattr(buffer, k) is not None}
    part = path.with_name(path.name + ".part")
    with open(part, "wb") as file:
        np.savez(file, pos=buffer.pos, full=buffer.full, **arrays)
    part.replace(path)


def load_buffer(buffer, path: Path) -> None:
    """Fill SB3's ``ReplayBuffer`` from :func:`save_buffer`'s file, read with ``allow_pickle=False``.
    ``ValueError`` naming the file when it is missing (an older bimp's pickled ``.pkl`` is not read) or does
    not fit ``buffer``."""
    if not path.is_file():
        old = path.with_suffix(".pkl")
        raise ValueError(f"no replay buffer {path}" + (
            f"; {old.name} is a pickled one (an older bimp), not read because unpickling a file can run code"
            if old.is_file() else "") + ": train into a new --out, or delete checkpoints/ to start over")
    try:
        with np.load(path, allow_pickle=False) as saved:
            pos, full = int(saved["pos"]), bool(saved["full"])
            rows = buffer.buffer_size if full else pos
            if not 0 <= pos < buffer.buffer_size:
                raise ValueError(f"pos {pos} outside [0, {buffer.buffer_size})")
            for key in _BUFFER_ARRAYS:
                target = getattr(buffer, key)
                if target is None:
                    continue
                value = saved[key]
                if value.shape != (rows, *target.shape[1:]):
                    raise ValueError(f"{key} has shape {value.shape}, this run's buffer {(rows, *target.shape[1:])}")
                target[:rows] = value
    except (ValueError, KeyError, OSError, zipfile.BadZipFile) as err:
        raise ValueError(f"{path} is not a replay buffer of this run ({_brief(err)}); train into "
                         f"a new --out, or delete checkpoints/ to start over") from None
    buffer.pos, buffer.full = pos, full


def _checkpoint_callback(cfg: RLConfig, out: Path):
    """SB3's ``CheckpointCallback`` every ``cfg.checkpoint_every`` timesteps, SAC's replay buffer written by
    :func:`save_buffer` (no pickle) and before its checkpoint: a checkpoint on disk always has its buffer."""
    from stable_baselines3.common.callbacks import CheckpointCallback

    class Checkpoints(CheckpointCallback):
        def _on_step(self) -> bool:
            if self.n_calls % self.save_freq == 0 and getattr(self.model, "replay_buffer", None) is not None:
                checkpoint = Path(self._checkpoint_path(extension="zip"))
                save_buffer(self.model.replay_buffer, _buffer_path(checkpoint))
            return super()._on_step()

    return Checkpoints(save_freq=max(cfg.checkpoint_every // cfg.n_envs, 1), save_path=str(out / "checkpoints"),
                       name_prefix=cfg.model_name.removesuffix(".zip"))


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


def make_model(cfg: RLConfig, venv):
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


def _check_same_run(cfg: RLConfig, out: Path) -> None:
    """Refuse to write into ``out`` when it holds another configuration's run: results never mix."""
    path = out / "config.json"
    if not path.is_file():
        return
    before = read_json(path)
    if not isinstance(before, dict):
        raise EvaluationError(f"{path} is not a training run's config (not a JSON object): train into a new --out")
    now = json.loads(json.dumps(asdict(cfg)))  # tuples as lists, as they were written
    differ = sorted(k for k in set(before) | set(now)
                    if before.get(k) != now.get(k) and k not in _RESUMABLE_CHANGES)
    if differ:
        changes = ", ".join(f"{k}: {before.get(k)!r} there, {now.get(k)!r} here" for k in differ)
        raise ValueError(f"{out} holds a run with other settings ({changes}); choose another folder")


def _monitor_files(out: Path) -> list[Path]:
    return sorted(out.glob("*.monitor.csv"), key=lambda p: int(p.name.split(".")[0]))


def _drop_replayed_episodes(out: Path, n_envs: int, segment_start: int, resume_at: int) -> None:
    """Cut the interrupted segment's monitor logs back to the checkpoint a run resumes from: the steps after it
    are played again by the resumed run, and would otherwise count twice in the curve. The envs step in lockstep,
    so at the checkpoint each env had played ``(resume_at - segment_start) / n_envs`` of the segment's steps."""
    budget = (resume_at - segment_start) / n_envs
    for log in _monitor_files(out)[-n_envs:]:
        lines = log.read_text().splitlines(keepends=True)
        kept, steps = lines[:2], 0  # the JSON header and the column names (r,l,t)
        for row in lines[2:]:
            steps += int(row.split(",")[1])
            if steps > budget:
                break
            kept.append(row)
        write_atomic(log, "".join(kept))


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
    _check_same_run(cfg, out)
    if _finished(cfg, out):
        return path
    # The nets are tiny: more threads only fight the env processes (and other users) for the cores.
    torch.set_num_threads(1)
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / "config.json", json.dumps(asdict(cfg), indent=2) + "\n")
    segments_file = out / "segments.json"  # the timesteps each segment (run, or resume) started from
    segments = read_json(segments_file) if segments_file.is_file() else [0]
    if not (isinstance(segments, list) and segments and all(type(n) is int and n >= 0 for n in segments)):
        raise EvaluationError(f"{segments_file} is not a list of step counts: train into a new --out")
    resume_at, checkpoint = _latest_checkpoint(out)
    if _monitor_files(out):
        _drop_replayed_episodes(out, cfg.n_envs, segments[-1], resume_at)
        segments.append(resume_at)
    write_atomic(segments_file, json.dumps(segments) + "\n")
    segment = len(_monitor_files(out)) // cfg.n_envs
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
    callbacks = [_checkpoint_callback(cfg, out)] if cfg.checkpoint_every else []
    if progress:
        callbacks.append(_progress_callback(cfg.timesteps))
    start = time.perf_counter()
    model.learn(total_timesteps=max(cfg.timesteps - done, 0), callback=callbacks, reset_num_timesteps=done == 0)
    wall = time.perf_counter() - start
    venv.close()
    model.save(path)
    write_atomic(out / "train_time.json", json.dumps({"wall_s": round(wall, 1), "timesteps": cfg.timesteps,
                                                      "resumed_at": done or None}) + "\n")
    plot_curve(out, out / "curve.png", title=f"{cfg.algo.upper()} {cfg.scenario} (seed {cfg.seed})")
    return path


def _finished(cfg: RLConfig, out: Path) -> bool:
    """Whether ``out`` holds ``cfg``'s finished run: its model and ``train_time.json``, written last."""
    return (out / cfg.model_name).is_file() and (out / "train_time.json").is_file()


def _wall_s(out: Path) -> float:
    """The training wall time [s] a finished run recorded."""
    wall = read_json(out / "train_time.json")
    if not (isinstance(wall, dict) and isinstance(wall.get("wall_s"), (int, float))):
        raise EvaluationError(f"{out / 'train_time.json'} holds no wall_s")
    return float(wall["wall_s"])


def plot_curve(monitor_dir: Path, path: Path, title: str = "") -> None:
    """Episode return against timesteps from the Monitor logs in ``monitor_dir``, with a moving mean."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from stable_baselines3.common.monitor import load_results

    df = load_results(str(monitor_dir))  # episodes of all envs, ordered by wall time
    steps, returns = np.cumsum(df["l"].to_numpy()), df["r"].to_numpy()
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(steps, returns, ".", ms=2, alpha=0.3, label="episode")
    if len(returns) >= 2:
        w = max(1, min(50, len(returns) // 10))
        ax.plot(steps[w - 1:], np.convolve(returns, np.ones(w) / w, mode="valid"), label=f"mean of {w}")
    ax.set(xlabel="timesteps", ylabel="episode return", title=title)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    write_figure(fig, path, dpi=120)
    plt.close(fig)


# --- inference -----------------------------------------------------------------------------------------
class SB3Policy:
    """A trained SB3 model as a :class:`Policy`: the deterministic prediction on :func:`features` of the raw
    observation, mapped back to the env's normalized action by :func:`to_env_action`.

    The model file is read without unpickling (:func:`read_model_file`): a file from anywhere runs no code.
    ``trust_model=True`` loads it with SB3's own ``load`` instead, which unpickles it: only for a file whose
    source you trust, as it runs whatever code the file holds (docs/security.md).

    It reads ``env.unwrapped.scene`` at every ``act`` (the env rebuilds it at every reset). Deterministic:
    ``reset`` has nothing to seed.
    """

    def __init__(self, env: gym.Env, model_path: str | Path, algo: str, trust_model: bool = False):
        path = Path(model_path)
        if not path.is_file():
            raise FileNotFoundError(f"no {algo.upper()} model at {path}")
        if not isinstance(trust_model, bool):
            raise ValueError(f"trust_model must be true or false, got {trust_model!r}")
        self.env, self.algo, self.model_path = env, algo, path
        self.step_info: dict = {}  # a deterministic network: nothing to say about a step
        # The file is identified by its content, never by where it lies: a path would tie the config's hash (and
        # every record) to the machine and folder it was made in. Where it lies is shown apart, as an artifact.
        # trust_model enters the config only when set: the default config is as it was before it existed.
        self.config = {"algo": algo, "model_sha256": file_sha256(path)}
        if trust_model:
            self.config["trust_model"] = True
        self.artifacts = {"model": artifact_name(path, model_path)}
        # The SB3 policy (an ActorCriticPolicy or SACPolicy); its predict is the algorithm's.
        self.model = _load_trusted(path, algo, env) if trust_model else _load_safe(path, algo, env)

    def act(self, obs: np.ndarray) -> np.ndarray:
        scene = self.env.unwrapped.scene
        obs = scene.check_obs(obs)
        action, _ = self.model.predict(features(obs, scene), deterministic=True)
        return to_env_action(action, obs, scene)

    def reset(self, seed: int | None = None) -> None:
        pass


def artifact_name(path: Path, given: str | Path) -> str:
    """How a record names a model file: ``bimp:agents/models/NAME`` for a shipped one (relative to the package, the
    same on every machine), else the path as the user gave it."""
    if path.resolve().parent == MODEL_DIR.resolve():
        return f"bimp:agents/models/{path.name}"
    return str(given)


def _scenario_of(env: gym.Env) -> str | None:
    """The scenario of an env made by ``gym.make(envs.env_id(...))``; None for any other env."""
    spec = env.spec or env.unwrapped.spec
    return envs.scenario_name(spec.id) if spec is not None else None


def shipped_name(algo: str, scenario: str, training_seed: int) -> str:
    """File name of a shipped model under ``agents/models/``: ``{algo}_{scenario}_s{training_seed}.zip``."""
    return model_name(algo, scenario).replace(".zip", f"_s{training_seed}.zip")


def default_training_seeds() -> dict[str, int]:
    """``{"{algo}_{scenario}": training seed}`` of the shipped defaults (``agents/models/defaults.json``: the
    median of the shipped training seeds on the tuning seeds, docs/rl.md)."""
    path = MODEL_DIR / "defaults.json"
    return json.loads(path.read_text()) if path.is_file() else {}


def _shipped_model(env: gym.Env, algo: str, training_seed: int | None) -> Path:
    scenario = _scenario_of(env)
    if scenario is None:
        raise ValueError(f"cannot tell the scenario of {env}: make it with gym.make(envs.env_id(...)) "
                         f"or pass model=")
    key = model_name(algo, scenario).removesuffix(".zip")
    if training_seed is None:
        training_seed = default_training_seeds().get(key)
    path = MODEL_DIR / shipped_name(algo, scenario, training_seed) if training_seed is not None else None
    if path is None or not path.is_file():
        shipped = sorted(p.name for p in MODEL_DIR.glob(f"{key}_s*.zip"))
        raise FileNotFoundError(
            f"no {algo.upper()} model is shipped for {scenario}"
            + (f" with training seed {training_seed} (shipped: {shipped})" if shipped else "")
            + f"; train one with `bimp train-rl --scenario {scenario} --algo {algo}` and pass model=")
    return path


def make_ppo(env: gym.Env, *, model: str | Path | None = None, training_seed: int | None = None,
             trust_model: bool = False) -> SB3Policy:
    """The PPO baseline for ``env``: the shipped model of its scenario trained with ``training_seed`` (default:
    the shipped default, :func:`default_training_seeds`), or the file ``model``. ``trust_model=True`` loads it
    with SB3's ``load``, which unpickles it and so runs any code it holds: only for a file you trust (by default
    it is read without unpickling, docs/security.md)."""
    return SB3Policy(env, model or _shipped_model(env, "ppo", training_seed), "ppo", trust_model)


def make_sac(env: gym.Env, *, model: str | Path | None = None, training_seed: int | None = None,
             trust_model: bool = False) -> SB3Policy:
    """The SAC baseline for ``env``, as :func:`make_ppo`."""
    return SB3Policy(env, model or _shipped_model(env, "sac", training_seed), "sac", trust_model)


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
        cfg = RLConfig.from_mapping(values)
        finished = _finished(cfg, Path(out))
        path = train(cfg, Path(out), progress=False)
        report: dict[str, Any] = {"run": out, "model": str(path), "earlier": finished, "wall_s": _wall_s(Path(out))}
        if seeds:
            report["check"] = check_model(cfg, path, Path(out), seeds)
    except Exception as err:  # noqa: BLE001 -- one run's failure is its report: hours of the others go on
        return [{"run": out, "error": f"{type(err).__name__}: {err}"}]
    return [report]


def _job_crashed(job: tuple[dict[str, Any], str, int], why: str) -> list[dict[str, Any]]:
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


# --- command line --------------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bimp train-rl", description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", nargs="+", action="extend", required=True,
                        help=f"one or more of {sorted(envs.SCENARIOS)}")
    parser.add_argument("--algo", choices=ALGOS, default="ppo")
    parser.add_argument("--timesteps", type=int, default=None, help="total env steps (default: RLConfig's)")
    parser.add_argument("--seed", type=int, nargs="+", action="extend", default=None,
                        help="training seed(s) (default: RLConfig's)")
    parser.add_argument("--n-envs", type=int, default=None)
    parser.add_argument("--vec-env", choices=("dummy", "subproc"), default=None,
                        help="step the envs in this process (dummy, one core) or one process each (subproc)")
    parser.add_argument("--config", type=Path, help="YAML file of RLConfig overrides (unknown keys are errors)")
    # str, not Path: Path("") is "." and would pass the empty-name check as the current folder.
    parser.add_argument("--out", help="one run's output folder (default RUNS_DIR/{algo}_{scenario}_s{seed})")
    parser.add_argument("--runs-dir", default=None, help="where the runs' folders go, each under its "
                        "default name (default runs/rl); on a Ray cluster of several machines, a disk every node "
                        "mounts at the same path")
    parser.add_argument("--workers", type=int, default=1, help="runs trained at once on this machine (default 1)")
    add_backend_arguments(parser)
    parser.add_argument("--eval-seeds", type=int, default=5, help="episodes of the final check against the zero "
                        "action (0: skip)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)

    def fail(error: object) -> NoReturn:
        parser.exit(2, f"bimp train-rl: error: {error}\n")

    values: dict[str, Any] = {}
    if args.config:
        try:
            data = read_yaml(args.config)
        except ValueError as err:
            fail(err)
        if data is not None and not isinstance(data, dict):
            fail(f"{args.config}: expected a mapping of RLConfig overrides, got {type(data).__name__}")
        values.update(data or {})
    values["algo"] = args.algo
    for key in ("timesteps", "n_envs", "vec_env"):
        if getattr(args, key) is not None:
            values[key] = getattr(args, key)
    runs: list[tuple[RLConfig, Path]] = []
    try:
        if args.workers < 1 or args.eval_seeds < 0:
            raise ValueError(f"--workers must be >= 1 and --eval-seeds >= 0, got {args.workers} and "
                             f"{args.eval_seeds}")
        if args.out is not None and args.runs_dir is not None:
            raise ValueError("--out names one run's folder, --runs-dir the folder of the runs' folders: give one")
        check_backend(args.backend, args.address, args.ray_cpus)
        runs_dir = (check_out_dir(args.runs_dir, create=False, flag="--runs-dir") if args.runs_dir is not None
                    else Path("runs/rl"))
        one_out = check_out_dir(args.out, create=False) if args.out is not None else None
        for scenario in args.scenario:
            scenario = envs.scenario_name(envs.env_id(scenario)) or scenario  # one name per scenario, one folder
            for seed in args.seed or [values.get("seed")]:
                cfg = RLConfig.from_mapping({**values, "scenario": scenario,
                                             **({"seed": seed} if seed is not None else {})})
                runs.append((cfg, one_out or runs_dir / run_name(cfg)))
        if len(runs) > 1 and one_out:
            raise ValueError("--out names one run's folder; several runs each go to --runs-dir/"
                             "{algo}_{scenario}_s{seed}")
        names = [run_name(cfg) for cfg, _ in runs]
        twice = sorted({name for name in names if names.count(name) > 1})
        if twice:
            raise ValueError(f"run(s) {twice} named twice: give each scenario and seed once")
        for cfg, out in runs:  # every run's folder before the first trains: no refusal hours in
            check_out_dir(out, create=False, flag="--out" if one_out else "--runs-dir")
            _check_same_run(cfg, out)
    except (BackendError, EvaluationError, TypeError, ValueError) as err:
        fail(err)
    if len(runs) == 1 and args.backend == "local":
        return _train_one(*runs[0], args, fail)
    return _train_many(runs, args, fail)


def _train_one(cfg: RLConfig, out: Path, args: argparse.Namespace, fail: Callable[[object], NoReturn]) -> int:
    """One run in this process, with a progress bar over its timesteps."""
    try:
        path = train(cfg, out, progress=not args.no_progress)
    except (EvaluationError, ValueError) as err:  # a checkpoint that does not fit
        fail(err)
    print(f"model: {path}\ncurve: {out / 'curve.png'}\n"
          f"train wall time: {_wall_s(out)} s")
    if args.eval_seeds:
        for who, r in check_model(cfg, path, out, args.eval_seeds).items():
            print(f"{who:>6}: progress {r['progress']:.1f} m, collisions {r['collision']:.2f}, "
                  f"off-road {r['offroad']:.2f}, return {r['return']:.1f}")
    return 0


def _train_many(runs: list[tuple[RLConfig, Path]], args: argparse.Namespace,
                fail: Callable[[object], NoReturn]) -> int:
    """The runs on the backend, a progress bar over runs and a line per run as it ends; 1 when any failed."""
    from tqdm import tqdm

    try:
        start_backend(args.backend, args.address, args.ray_cpus)
    except BackendError as err:
        fail(err)
    # Absolute: a Ray worker's working folder is not this one (on a cluster the folder must be on a shared disk).
    jobs = [(asdict(cfg), str(out.resolve()), args.eval_seeds) for cfg, out in runs]
    failed = []
    with tqdm(total=len(jobs), desc="runs", unit="run", disable=args.no_progress) as bar:
        def write(report: dict[str, Any]) -> None:
            failed.extend([report] if "error" in report else [])
            bar.update()
            tqdm.write(report_line(report))

        run_groups(jobs, train_job, _job_crashed, write, backend=args.backend, workers=args.workers,
                   address=args.address, cpus=args.ray_cpus)
    if failed:
        print(f"{len(failed)} of {len(jobs)} runs failed; the same command trains them again, each from its last "
              f"checkpoint")
        return 1
    return 0
