"""Reinforcement-learning baseline: stable-baselines3 PPO or SAC, acting through the :class:`Policy` protocol.

Inference: ``make_policy("ppo", env)`` loads the default training seed's model of the env's scenario
(``agents/models/{algo}_{scenario}_s{seed}.zip``, the default in ``agents/models/defaults.json``), the scenario
taken from ``env.spec.id``; ``training_seed=S`` picks another shipped seed, ``model=PATH`` any file. A model
records the scenario it was trained on and is refused on another's env. Over training seeds: ``bimp aggregate``.
Training (``bimp train-rl``, checkpoints, resuming, many runs at once): :mod:`bimp.agents.rl_train`.

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

import io
import json
import pickle
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.policies import ActorCriticPolicy, BasePolicy
from stable_baselines3.sac.policies import SACPolicy

from bimp import envs
from bimp.agents.files import read_json_or
from bimp.configs import ConfigError, check_fields, file_sha256
from bimp.envs.wrappers import PlanningWrapper, features, n_features, to_env_action

MODEL_DIR = Path(__file__).resolve().parent / "models"
ALGOS = ("ppo", "sac")


# --- configuration -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RLConfig:
    """One training run. ``batch_size=None`` takes the algorithm's usual value (PPO 64, SAC 256);
    ``n_steps``, ``n_epochs``, ``ent_coef`` and ``gae_lambda`` are PPO's, ``buffer_size``, ``learning_starts``
    and ``tau`` SAC's. ``vec_env``: ``"dummy"`` steps the envs in this process (one core), ``"subproc"`` one
    process each. ``checkpoint_every``: timesteps between checkpoints (0: none). Built and checked as every config
    is (``load_config(RLConfig, FILE, **overrides)``): an unknown key refused by name, a bad value by
    :class:`ConfigError` (an unknown scenario by ``ValueError`` naming the choices)."""

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
        for key, allowed in (("algo", ALGOS), ("vec_env", ("dummy", "subproc"))):
            if getattr(self, key) not in allowed:
                raise ConfigError(key, f"one of {allowed}", getattr(self, key))
        for key in ("timesteps", "n_envs", "n_steps", "n_epochs", "buffer_size", "learning_rate", "tau"):
            if not getattr(self, key) > 0:
                raise ConfigError(key, "> 0", getattr(self, key))
        for key in ("ent_coef", "learning_starts", "checkpoint_every"):
            if getattr(self, key) < 0:
                raise ConfigError(key, ">= 0", getattr(self, key))
        if self.batch_size is not None and self.batch_size < 2:
            raise ConfigError("batch_size", "None or an int >= 2", self.batch_size)
        if not self.net_arch or min(self.net_arch) < 1:
            raise ConfigError("net_arch", "a non-empty list of positive widths", self.net_arch)
        if not 0.0 < self.gamma <= 1.0:
            raise ConfigError("gamma", "in (0, 1]", self.gamma)
        if not 0.0 <= self.gae_lambda <= 1.0:
            raise ConfigError("gae_lambda", "in [0, 1]", self.gae_lambda)

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


def error_brief(err: Exception) -> str:
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
                         f"({error_brief(err)}); {how}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: its data entry is not a JSON object; {how}")
    plain = {k: v for k, v in data.items() if not (isinstance(v, dict) and ":serialized:" in v)}
    return plain, state_dicts, variables or {}


def _check_record(path: Path, meta: Any, algo: str, env: gym.Env, trained_on: str | None = None) -> None:
    """Refuse a model whose ``bimp`` record (written by :func:`train`) is missing or names another algorithm,
    scenario or feature count than ``env``'s. ``trained_on``: the scenario the model must record instead of
    ``env``'s, accepted only where the two are difficulties of one family (:func:`same_family`)."""
    if not isinstance(meta, dict) or not {"scenario", "algo", "n_features"} <= set(meta):
        raise ValueError(f"{path} was not written by `bimp train-rl` (it records no scenario); retrain it")
    if meta["algo"] != algo:
        raise ValueError(f"{path} is a {str(meta['algo']).upper()} model, not {algo.upper()}")
    scenario = _scenario_of(env)
    if trained_on is not None and meta["scenario"] != trained_on:
        raise ValueError(f"{path} was trained on {meta['scenario']}, not {trained_on} (trained_on)")
    if scenario is not None and meta["scenario"] != scenario and trained_on is None:
        raise ValueError(f"{path} was trained on {meta['scenario']}, not {scenario}: its features mean other "
                         f"things there (another difficulty of its family: give trained_on={meta['scenario']})")
    n = n_features(env.unwrapped.scene)
    if meta["n_features"] != n:
        raise ValueError(f"{path} expects {meta['n_features']} features; this feature set gives {n}")


def _load_safe(path: Path, algo: str, env: gym.Env, trained_on: str | None = None) -> BasePolicy:
    """The deterministic SB3 policy of the model file ``path`` rebuilt from plain data, nothing unpickled:
    ``FEATURE_POLICIES[algo]`` on ``env``'s :class:`PlanningWrapper` spaces (features ``(n,)``, action ``(2,)``
    in [-1, 1]), the file's ``policy_kwargs`` (``net_arch``) and its ``policy`` state dict, loaded strict."""
    data, state_dicts, _ = read_model_file(path)
    _check_record(path, data.get("bimp"), algo, env, trained_on)
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
                         f"features ({error_brief(err)}); {_HOW}") from None
    policy.set_training_mode(False)
    return policy


def _load_trusted(path: Path, algo: str, env: gym.Env, trained_on: str | None = None) -> BasePolicy:
    """The policy of ``path`` by SB3's own ``load``, which unpickles the file: whatever code it holds runs.
    Only behind ``trust_model=True``."""
    # Schedules are pickled closures; replacing them keeps loading independent of the training Python.
    custom = {"learning_rate": 0.0, "lr_schedule": lambda _: 0.0, "clip_range": lambda _: 0.0}
    model = _algo_class(algo).load(path, device="cpu", custom_objects=custom)
    _check_record(path, getattr(model, "bimp", None), algo, env, trained_on)
    if model.observation_space.shape != (n_features(env.unwrapped.scene),) or model.action_space.shape != (2,):
        raise ValueError(f"{path} expects observations {model.observation_space.shape} and actions "
                         f"{model.action_space.shape}; this feature set gives "
                         f"({n_features(env.unwrapped.scene)},) and (2,)")
    return model.policy


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

    def __init__(self, env: gym.Env, model_path: str | Path, algo: str, trust_model: bool = False,
                 trained_on: str | None = None):
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
        trained_on = _trained_on(env, trained_on)
        if trained_on is not None:
            self.config["trained_on"] = trained_on
        self.artifacts = {"model": artifact_name(path, model_path)}
        # The SB3 policy (an ActorCriticPolicy or SACPolicy); its predict is the algorithm's.
        load = _load_trusted if trust_model else _load_safe
        self.model = load(path, algo, env, trained_on)

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


def same_family(a: str, b: str) -> bool:
    """Whether scenarios ``a`` and ``b`` are difficulties of one family (``cut-in-hard``, ``cut-in-extreme``): one
    env class, whose features mean the same things at every difficulty."""
    return envs.scenario_spec(a).entry_point == envs.scenario_spec(b).entry_point


def _trained_on(env: gym.Env, trained_on: str | None) -> str | None:
    """``trained_on`` by its scenario name, checked against ``env``'s scenario: ``ValueError`` naming both where
    they are not one family."""
    if trained_on is None:
        return None
    name = envs.scenario_spec(trained_on).name  # ValueError naming the choices
    scenario = _scenario_of(env)
    if scenario is None or not same_family(name, scenario):
        raise ValueError(f"trained_on={name}: a model of {name} does not drive {scenario or env}, which is not a "
                         f"difficulty of its family (its features mean other things there)")
    return name


def _scenario_of(env: gym.Env) -> str | None:
    """The scenario of an env made by ``gym.make(envs.env_id(...))``; None for any other env."""
    spec = env.spec or env.unwrapped.spec
    return envs.scenario_name(spec.id) if spec is not None else None


def shipped_name(algo: str, scenario: str, training_seed: int) -> str:
    """File name of a shipped model under ``agents/models/``: ``{algo}_{scenario}_s{training_seed}.zip``."""
    return model_name(algo, scenario).replace(".zip", f"_s{training_seed}.zip")


def default_training_seeds() -> dict[str, int]:
    """``{"{algo}_{scenario}": training seed}`` of the shipped defaults (``agents/models/defaults.json``: the
    best of the shipped training seeds on the tuning seeds, docs/rl.md)."""
    return read_json_or(MODEL_DIR / "defaults.json", {})


def _shipped_model(env: gym.Env, algo: str, training_seed: int | None, trained_on: str | None = None) -> Path:
    """The shipped model of ``env``'s scenario (or of ``trained_on``, another difficulty of its family)."""
    scenario = _trained_on(env, trained_on) or _scenario_of(env)
    if scenario is None:
        raise ValueError(f"cannot tell the scenario of {env}: make it with gym.make(envs.env_id(...)) "
                         f"or pass model=")
    key = model_name(algo, scenario).removesuffix(".zip")
    if training_seed is None:
        training_seed = default_training_seeds().get(key)
    path = MODEL_DIR / shipped_name(algo, scenario, training_seed) if training_seed is not None else None
    if path is None or not path.is_file():
        shipped = sorted(p.name for p in MODEL_DIR.glob(f"{key}_s*.zip"))
        kin = sorted({name for name in envs.SCENARIOS if name != scenario and same_family(name, scenario)
                      and any(MODEL_DIR.glob(f"{model_name(algo, name).removesuffix('.zip')}_s*.zip"))})
        raise FileNotFoundError(
            f"no {algo.upper()} model is shipped for {scenario}"
            + (f" with training seed {training_seed} (shipped: {shipped})" if shipped else "")
            + (f"; its family's models drive it with trained_on={kin[0]}" if kin and not shipped else "")
            + f"; train one with `bimp train-rl --scenario {scenario} --algo {algo}` and pass model=")
    return path


def make_ppo(env: gym.Env, *, model: str | Path | None = None, training_seed: int | None = None,
             trust_model: bool = False, trained_on: str | None = None) -> SB3Policy:
    """The PPO baseline for ``env``: the shipped model of its scenario trained with ``training_seed`` (default:
    the shipped default, :func:`default_training_seeds`), or the file ``model``. ``trained_on``: a model of
    another difficulty of ``env``'s family (``cut-in-hard`` on ``cut-in-extreme``); refused for another family.
    ``trust_model=True`` loads it with SB3's ``load``, which unpickles it and so runs any code it holds: only for a
    file you trust (by default it is read without unpickling, docs/security.md)."""
    path = model or _shipped_model(env, "ppo", training_seed, trained_on)
    return SB3Policy(env, path, "ppo", trust_model, trained_on)


def make_sac(env: gym.Env, *, model: str | Path | None = None, training_seed: int | None = None,
             trust_model: bool = False, trained_on: str | None = None) -> SB3Policy:
    """The SAC baseline for ``env``, as :func:`make_ppo`."""
    path = model or _shipped_model(env, "sac", training_seed, trained_on)
    return SB3Policy(env, path, "sac", trust_model, trained_on)


# --- replay buffers, read and written without pickle ----------------------------------------------------
_BUFFER_ARRAYS = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")


def buffer_path(checkpoint: Path) -> Path:
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
        raise ValueError(f"{path} is not a replay buffer of this run ({error_brief(err)}); train into "
                         f"a new --out, or delete checkpoints/ to start over") from None
    buffer.pos, buffer.full = pos, full
