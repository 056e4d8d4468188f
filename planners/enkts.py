"""EnKTS and EnKS as policies: thin stateful adapters around the pure JAX core (:mod:`bimp.planners.core`).

EnKS is the same planner with ``nu = inf`` (Gaussian draws, no spread adaptation): a special case, not a copy. The
adapter checks the observation (outside the compiled function, so a bad one raises a clear ``ValueError``), builds
the planning problem of the env's current scene (:mod:`bimp.planners.problem`), keeps the warm start and the episode's
PRNG key, and counts fallbacks. The same policy plans a batch: ``reset(seed=[s1, ..., sB])`` then
``act(obs (B, obs_dim)) -> (B, 2)``, one compiled call, row ``i`` equal to a single planner reset with ``s_i``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from bimp.configs import ConfigError, added_field, check_fields
from bimp.envs.scene import Scene, asks_guard, leads, real_array, scene_batch
from bimp.planners import core
from bimp.planners.dynamics import dynamics_files, steer_bound
from bimp.planners.guard import guarded
from bimp.planners.model import model_params
from bimp.planners.problem import (
    BarrierShape,
    Problem,
    ProblemConfig,
    Road,
    for_road,
    load_planner_config,
    make_problem,
    road_changes,
    road_window,
)
from bimp.planners.problem import search_space as problem_search_space


@dataclass(frozen=True)
class EnKTSConfig:
    """EnKTS's settings and its planning problem. Units: m, rad, s, m/s, m/s^2; increments per control step.

    problem: the virtual system (:class:`bimp.planners.problem.ProblemConfig`: horizon, nu, sigma_du, sigma_ref,
    sigma_input, sigma_barrier, lane_change_rate, barrier, dynamics; ``problem.nu = inf`` is EnKS), as every
    planner holds it; n_particles: ensemble size N >= 2; adapt_spread: rescale the posterior
    anomalies by the Student's-t factor; grow_nu: ``nu <- nu + m`` after each update (eq. 19); max_spread: cap on
    that factor (``inf``: none); max_innovation: how many predicted standard deviations the virtual observation may
    lie from the predicted mean, per row and step; relaxation: share of the spread an update removed that is given
    back (0 = none); iterations: smoothing passes per step (1 = the paper's single pass); gate_barriers: a barrier
    that no particle touches sits out the update (``bimp.planners.core._active``); first_control_barriers: the applied
    control's bounds are measured at every step; update: the reading of the printed eq. 16, ``"perturbed"`` (ours),
    ``"deterministic"`` (the authors' public EnKS code) or ``"literal"`` (:func:`bimp.planners.core.student_t_update`);
    road_guard: where the smoothed plan leaves the road, brake in lane instead (:mod:`bimp.planners.guard`): True
    on every road, False on none, None (the default) where the road asks for it (``Scene.edge_guard``: highway-env's
    roads and the families; the paper's scenarios keep the planner as printed), recorded as a road change;
    seed: default seed of the planner's key. The switches exist for the ablation and the readings study
    (``docs/reproduction.md``); the defaults are what that study supports. Values are checked by
    :func:`bimp.configs.check_fields` (types, lengths) and then for range: a bad one raises
    :class:`bimp.configs.ConfigError` naming the key and the value.
    """

    n_particles: int = 50
    adapt_spread: bool = True
    grow_nu: bool = True
    max_spread: float = 25.0
    max_innovation: float = 2.0
    relaxation: float = 0.5
    iterations: int = 1
    # Added for the claims study, with the behaviour from before as their neutral value (configs.added_field).
    gate_barriers: bool = added_field(True, neutral=True)
    first_control_barriers: bool = added_field(True, neutral=True)
    update: str = added_field("perturbed", neutral="perturbed")
    # Brake in lane where the smoothed plan leaves the road (bimp.planners.guard); off reproduces the planner before,
    # and so does None where the road does not ask for it (where it does, the planner's `road` records it).
    road_guard: bool | None = added_field(None, neutral=False, by_road=(None,))
    seed: int = 0
    problem: ProblemConfig = field(default_factory=ProblemConfig)

    def __post_init__(self) -> None:
        check_fields(self, allow_inf=("max_spread",))  # types, lengths; a problem mapping -> ProblemConfig
        if self.n_particles < 2:
            raise ConfigError("n_particles", "an int >= 2", self.n_particles)
        if self.iterations < 1:
            raise ConfigError("iterations", "an int >= 1", self.iterations)
        if not self.max_spread >= 1:
            raise ConfigError("max_spread", ">= 1 (inf: no cap)", self.max_spread)
        if not self.max_innovation > 0:
            raise ConfigError("max_innovation", "> 0", self.max_innovation)
        if not 0 <= self.relaxation < 1:
            raise ConfigError("relaxation", "in [0, 1)", self.relaxation)
        if self.seed < 0:
            raise ConfigError("seed", "an int >= 0", self.seed)
        if self.update not in core.READINGS:
            raise ConfigError("update", f"one of {', '.join(core.READINGS)}", self.update)

    def settings(self, n_obstacles: int, steer: float) -> core.Settings:
        """The static part for :func:`bimp.planners.core.plan_step` on a road with ``n_obstacles`` slots and the
        planning steering bound ``steer`` [rad] (:func:`bimp.planners.problem.for_road`)."""
        problem = for_road(self.problem, steer)
        return core.Settings(self.n_particles, problem.horizon, n_obstacles, float(problem.nu),
                             self.adapt_spread and not math.isinf(problem.nu), self.grow_nu, float(self.max_spread),
                             float(self.max_innovation), float(self.relaxation), self.iterations,
                             tuple(float(s) for s in problem.sigma_du), self.gate_barriers,
                             self.first_control_barriers, self.update)


@dataclass(frozen=True)
class Plan:
    """The latest plan: ``controls (H, 2)`` smoothed mean ``[a, delta]``, ``states (H + 1, 4)`` rolled out from
    the current state with those controls, ``control_particles (N, H, 2)`` the smoothed ensemble (a leading
    ``B`` on each for a batch)."""

    states: np.ndarray
    controls: np.ndarray
    control_particles: np.ndarray


def _key(seed: int) -> jax.Array:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be an int >= 0, got {seed!r}")
    return jax.random.key(int(seed))


class EnKTSPlanner:
    """EnKTS (``nu < inf``) or EnKS (``nu = inf``) as a :class:`bimp.agents.Policy`.

    scene: a :class:`bimp.envs.Scene` or a callable returning the current one (``lambda: env.unwrapped.scene``: the road
    is redrawn at every env reset); for a batch, a callable returning one scene per row.

    ``fallbacks`` counts plans (rows, for a batch) that came out non-finite and were replaced by holding the last
    input; ``step_info`` says what the last ``act`` did: ``{"fallback": bool}``, for a batch one bool per row
    (``{"fallback": (b_1, .., b_B)}``). The episode loops record it per step (:mod:`bimp.agents.rollout`).
    """


    def __init__(self, scene: Scene | Callable[[], Scene | Sequence[Scene]], config: EnKTSConfig = EnKTSConfig()):
        self.config = config
        self._scene = scene if callable(scene) else (lambda: scene)
        built = scene_batch(self._scene())  # the scenes at build: what the road asks of the planner
        bound = steer_bound(built)  # the model must cover the road's steering bound
        self.files, self.artifacts = dynamics_files(config.problem.dynamics, bound)  # the weights by content and name
        # what the road changes in the problem (and whether it asks for the guard), for the record
        self.road = road_changes(config.problem, bound, leads(built))
        asked = asks_guard(built)
        self.guard = asked if config.road_guard is None else config.road_guard
        if config.road_guard is None and asked:
            self.road["road_guard"] = True
        self._model = jax.device_put(model_params(config.problem.dynamics, bound))
        self._problem_scenes: list[Scene] = []
        self._problem: Problem | None = None
        self.fallbacks = 0  # plans that came out non-finite and were replaced by holding the last input
        self.reset(config.seed)

    def reset(self, seed: int | Sequence[int] | None = None) -> None:
        """Start a new episode (or a batch of them, one seed each): new key(s), no warm start."""
        seed = self.config.seed if seed is None else seed
        self.batch = None if isinstance(seed, (int, np.integer)) else len(seed)
        if self.batch is None:
            self._keys = _key(seed)
            self._carry = core.initial_carry(self.config.problem.horizon)
        else:
            if self.batch < 1:
                raise ValueError("reset(seed=[...]) needs at least one seed")
            self._keys = jnp.stack([_key(s) for s in seed])
            self._carry = jax.tree.map(lambda a: jnp.broadcast_to(a, (self.batch, *a.shape)),
                                       core.initial_carry(self.config.problem.horizon))
        self._step = 0
        self._last: tuple | None = None  # (current states, PlanOut)
        self.step_info: dict = {}

    # --- Policy ---------------------------------------------------------------------------------------------
    def act(self, obs: np.ndarray) -> np.ndarray:
        """Normalized action ``(2,)`` float32 in [-1, 1], the smoothed mean of the first control; for a batch,
        ``obs (B, obs_dim)`` -> ``(B, 2)``. Raises ``ValueError`` on an observation of the wrong shape or dtype
        (real numbers only) or with non-finite entries."""
        scenes = scene_batch(self._scene())
        if (self.batch or 1) != len(scenes):
            raise ValueError(f"the planner was reset for {self.batch or 1} episode(s) but the scene callable gives "
                             f"{len(scenes)}")
        obs = real_array(obs, "observation").astype(float)
        rows = [obs] if self.batch is None else list(obs) if obs.ndim == 2 and len(obs) == self.batch else None
        if rows is None:
            raise ValueError(f"a batch of {self.batch} needs observations ({self.batch}, obs_dim), got {obs.shape}")
        obs = np.stack([scene.check_obs(row) for scene, row in zip(scenes, rows)]).astype(np.float32)
        problem = self._problem_of(scenes, obs)
        cfg = self.config.settings(scenes[0].n_obstacles, scenes[0].bounds.steer)
        # One key per episode, one draw per step: fold the step count into the episode's key.
        if self.batch is None:
            key = jax.random.fold_in(self._keys, self._step)
            action, self._carry, plan = core.plan_step(problem, cfg, self._carry, obs[0], key)
        else:
            keys = jax.vmap(jax.random.fold_in, in_axes=(0, None))(self._keys, self._step)
            action, self._carry, plan = core.plan_batch(problem, cfg, self._carry, obs, keys)
        self._step += 1
        self._last = (obs[0, :4] if self.batch is None else obs[:, :4], plan)  # states rolled out when asked
        fell_back = ~np.asarray(plan.ok)  # () or (B,)
        self.fallbacks += int(np.count_nonzero(fell_back))
        # Plain bools: the episode loop records them and the records summarize bool flags as fallback_steps.
        self.step_info = {"fallback": bool(fell_back) if self.batch is None else tuple(map(bool, fell_back))}
        action = np.asarray(action, dtype=np.float32)
        if self.guard:
            action = self._guard(scenes, action)
        return action

    def _guard(self, scenes: list[Scene], action: np.ndarray) -> np.ndarray:
        """``action`` with each row whose smoothed plan leaves the road replaced by braking in lane
        (:func:`bimp.planners.guard.guarded`); ``step_info["guard"]`` says where it acted."""
        states = self.plan.states  # (H + 1, 4) or (B, H + 1, 4): x_0 and the plan's x_1 .. x_H
        rows = [(guarded(scene, x[0], x[1:], a)) for scene, x, a in
                zip(scenes, states[None] if self.batch is None else states, action.reshape(-1, 2))]
        acted = tuple(flag for _, flag in rows)
        self.step_info["guard"] = acted[0] if self.batch is None else acted
        out = np.stack([a for a, _ in rows])
        return out[0] if self.batch is None else out

    @property
    def plan(self) -> Plan | None:
        """The latest plan (``None`` before the first ``act``)."""
        if self._last is None:
            return None
        x0, plan = self._last
        roll = core.roll_out if self.batch is None else jax.vmap(core.roll_out, in_axes=(None, 0, 0))
        states = roll(self._model, x0, plan.controls.astype(x0.dtype))
        return Plan(states=np.asarray(states, float), controls=np.asarray(plan.controls, float),
                    control_particles=np.asarray(plan.control_particles, float))

    def _problem_of(self, scenes: list[Scene], obs: np.ndarray) -> Problem:
        """The problem of the current scene(s) seen from each row's EV (``obs (B or 1, obs_dim)``): the road is a
        window of the scene's route ahead of the EV, rebuilt every step with the OVs' paths where the scene has them;
        the rest only when the rest of a scene changes (the env redraws it at reset; a wrapped highway-env env
        publishes a new scene, same but for its road and paths, every step). Compared by value, not ``id``: a freed
        scene's id can be reused by the next one."""
        static = [dataclasses.replace(s, road=None) for s in scenes]  # a Route compares by identity: leave it out
        if static != self._problem_scenes:
            problem = make_problem(scenes[0], self.config.problem, self._model)
            self._static = jax.device_put(jax.tree.map(
                lambda a: np.asarray(a, np.float32) if isinstance(a, (float, np.ndarray)) else a,
                problem._replace(road=None, paths=None)))
            self._problem_scenes = static
        roads = [road_window(s.road, row[:2], self.config.problem) for s, row in zip(scenes, obs)]
        road = roads[0] if self.batch is None else Road(*(np.stack(v) for v in zip(*roads)))
        # One program and one problem per batch: every row with the OVs' paths or none, and one reading of the
        # reference (make_problem reads the first scene's).
        if len({s.ov_paths is None for s in scenes}) > 1 or len({s.lane_path for s in scenes}) > 1:
            raise ValueError("a batch mixes scenes with the OVs' paths or a leading lane (junction roads, exit-v0) "
                             "and scenes without: batch episodes of one road")
        paths = None if scenes[0].ov_paths is None else np.stack([s.ov_paths for s in scenes]).astype(np.float32)
        if paths is not None and self.batch is None:
            paths = paths[0]
        return self._static._replace(road=Road(*(np.asarray(v, np.float32) for v in road)), paths=paths)


CONFIG_FILE = "planner.yaml"


def make_enkts(env, config: str | Path | None = None, **overrides) -> EnKTSPlanner:
    """EnKTS for ``env`` (or a list of envs: a batched planner, one row per env), configured in layers, each on top
    of the one before (:func:`bimp.planners.problem.load_planner_config`): the shared problem
    (``configs/problem.yaml``) as ``problem``, the shipped settings (``configs/planner.yaml``), the YAML ``config``
    if given (a file of overrides: a key it leaves out keeps its shipped value, so ``problem: {horizon: 30}`` alone
    keeps ``n_particles`` at the shipped 100 and the rest of the problem), then ``overrides``
    (``problem={"horizon": 30}`` or ``**{"problem.horizon": 30}``)."""
    return _planner(env, CONFIG_FILE, config, overrides)


def make_enks(env, config: str | Path | None = None, **overrides) -> EnKTSPlanner:
    """EnKS: the same tuning as EnKTS except ``problem.nu = inf`` (paper: "all other parameters the same"), set
    after ``config`` (so a config file shared with EnKTS keeps EnKS Gaussian) and before ``overrides``."""
    return _planner(env, CONFIG_FILE, config, {"problem": {"nu": math.inf}}, overrides)


def _planner(env, *layers) -> EnKTSPlanner:
    scenes = (lambda: [e.unwrapped.scene for e in env]) if isinstance(env, (list, tuple)) else \
        (lambda: env.unwrapped.scene)
    return EnKTSPlanner(scenes, load_planner_config(EnKTSConfig, *layers))


def search_space() -> dict:
    """What ``bimp tune`` searches for EnKTS (optuna distributions; keys as in :class:`EnKTSConfig`): the noise
    scales of the virtual system, the barriers' tightness and margins, nu (``problem.*``), the update's safeguards.
    N and H are not tuned: they set the compute, compared across values by ``bimp frontier``."""
    from optuna.distributions import FloatDistribution as Float

    return {
        **problem_search_space(),
        "problem.nu": Float(2.5, 30.0, log=True),
        "problem.sigma_barrier": Float(0.03, 0.5, log=True),
        "problem.lane_change_rate": Float(1.0, 4.0),
        "max_innovation": Float(1.0, 4.0),
        "relaxation": Float(0.0, 0.9),
    }


def enks_search_space() -> dict:
    """EnKTS's search space without nu (EnKS is its Gaussian case)."""
    return {k: v for k, v in search_space().items() if k != "problem.nu"}


__all__ = ["BarrierShape", "EnKTSConfig", "EnKTSPlanner", "Plan", "enks_search_space", "make_enkts", "make_enks",
           "search_space"]
