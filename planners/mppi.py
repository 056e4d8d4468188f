"""MPPI peer planner: ``pytorch_mppi.MPPI`` on the same MLP, minimizing the virtual system's negative log-likelihood.

MPPI (Williams et al. 2017) samples ``N`` control sequences around a nominal one, rolls them out and averages
them with weights ``exp(-cost / lambda)``. Here it optimizes exactly what EnKTS infers, in the Gaussian case:

    running cost  c_t = 0.5 * sum_i (h_i(xb_t) / sigma_i)^2,   h = bimp.planners.problem.measure (eq. 8, observed 0)
    sigma = [sigma_ref (3), sigma_input (2), sigma_barrier (one per barrier)]  of the config's problem

MPPI's state is the virtual system's block plus the first control: ``xb_t = [x_t (4), u_t (2), du_t (2), u_0 (2)]``
(eq. 7): ``u`` and ``du`` so the cost can charge input and rate terms, ``u_0`` because the virtual system observes the
applied control's barriers at every step. Its transition with MPPI's action ``u_t`` is ``x_{t+1} = f(x_t, u_t)``
(``x_0`` = the current state), ``du_t = u_t - u_{t-1}``; the start block carries ``u_{-1}`` = the input applied last,
so ``du_0`` is charged against it as EnKTS does. Like every planner here it measures the states ``x_1 .. x_H``,
each with the input that reached it.

Choices: the dynamics wrap :meth:`bimp.planners.dynamics.LearnedDynamics.predict` (numpy, tensors converted without
copies: float64 CPU tensors share memory with numpy): the same folded weights that EnKTS evaluates in JAX
(:func:`bimp.planners.model.model_params`), and the faster path at
N = 50 (about 4x, see ``docs/dynamics.md``; on par at N = 2000); the cost calls :func:`bimp.planners.problem.measure`,
numpy too (the one definition of the problem, evaluated with numpy arrays). Noise: by default MPPI's action is the
control *increment* (``sample: increments``), perturbed i.i.d. per step with ``noise_gain * sigma_du`` (the
virtual system's own prior on increments, eq. 7, its steering scaled to the road's bound by
:func:`bimp.planners.problem.for_road`) and clamped to the rate bounds; the input integrates it. The
literal alternative (``sample: inputs``) perturbs the inputs i.i.d.: with the shipped tuning its steering noise
(0.0015 rad) averages out over the horizon, no sample ever turns toward the reference lane, and any larger noise
breaks the steering rate bound (0.005 rad per step) at every step (on results seeds 1000-1199 it exceeded a rate
bound on 37% of overtaking steps and left the road on 71% of the episodes). Increments keep the rate bounds by
construction and let the steering wander far enough to change lanes. Temperature 1: the weights
``exp(-cost)`` are then the likelihood of the virtual observation, so the update is the importance-sampled
posterior mean under the sampling prior (the Bayesian reading of MPPI). Actions are clamped to the actuator
range (the env clips there); the planning bounds are the barriers' business, as for EnKTS. Warm start: the
previous nominal sequence shifted by one step (a zero increment, or the last input held, appended); the first
plan of an episode holds the last input.

What to expect: sampling increments is what made MPPI a peer. With inputs sampled (and the first wave's untuned
settings) it succeeded on 0.105 / 0.055 of the overtaking / emergency-brake results seeds, leaving the road on
most of the rest; with increments and the config ``bimp tune`` chose on training seeds (``configs/tuned/mppi.yaml``,
its default) it succeeded on every one of 200 episodes of each (``results/peers/``), at about 7 ms per step.

Randomness: pytorch_mppi 0.9.1 draws its noise with the global torch RNG (``torch.randn`` in ``_sample_noise``);
:class:`_SeededMPPI` overrides that one method to draw from a ``torch.Generator`` the planner owns, seeded in
``reset(seed)`` from the whole seed (:func:`generator_seed`), so the global RNG is never touched and the same seed
gives the same actions.

Cost per plan: H steps of O(N) model and cost work: linear in N and in H.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Literal

import numpy as np
import torch
from pytorch_mppi import MPPI

from bimp.configs import ConfigError, added_field, check_fields
from bimp.envs.scene import Scene, leads
from bimp.planners.dynamics import dynamics_files, model_from_name, steer_bound
from bimp.planners.problem import (
    Problem,
    ProblemConfig,
    for_road,
    load_planner_config,
    make_problem,
    measure,
    predict_obstacles,
    reference_profile,
    road_changes,
)
from bimp.planners.problem import search_space as problem_search_space

Dynamics = Callable[[np.ndarray, np.ndarray], np.ndarray]
NX = 10  # [x (4), u (2), du (2), u_0 (2)]


@dataclass(frozen=True)
class MPPIConfig:
    """MPPI's settings and its planning problem.

    problem: the virtual system (:class:`bimp.planners.problem.ProblemConfig`), as every planner holds it: its
    horizon is MPPI's, its noise scales and barriers make the cost, ``sigma_du`` the sampling noise and
    ``barrier.bound_margin`` tightens the rate bounds the increments are clamped to. The cost is the Gaussian
    negative log-likelihood, so ``problem.nu`` is not read (it stays the shared problem's, as recorded);
    n_particles: samples N >= 2 (EnKTS's default, 50); temperature: MPPI's lambda > 0, in units of the cost (a
    negative log-likelihood);
    noise_gain: std of the i.i.d. control perturbation per step as a multiple of ``problem.sigma_du`` (for the road:
    ``for_road``), > 0;
    control_cost: weight >= 0 of MPPI's control cost ``lambda U' Sigma^-1 eps`` (``1 - alpha`` of Williams et al.
    2018; 1 = pytorch_mppi's default). That term is the log-prior of controls that are zero-mean a priori; the
    virtual system's prior is on the increments and its input and rate terms are already in the running cost,
    so by default it is off (with it on, the steering feed-forward of a curve alone moves a plan's cost by tens,
    which pulled the plans straight off the road in the curve); sample: what MPPI perturbs, ``"increments"`` (its
    action is the control increment ``du``, clamped to the rate bounds, the input ``u`` part of its state) or
    ``"inputs"`` (its action is ``u``, perturbed i.i.d. per step); seed: default seed of the planner's generator.
    A bad value raises :class:`bimp.configs.ConfigError` naming the key and the value (types by
    :func:`bimp.configs.check_fields`).
    """

    n_particles: int = 50
    temperature: float = 1.0
    noise_gain: float = 1.0
    control_cost: float = 0.0
    # Added when MPPI was reworked (issue 14): it sampled the inputs before, so that is its neutral value.
    sample: Literal["increments", "inputs"] = added_field("increments", neutral="inputs")
    seed: int = 0
    problem: ProblemConfig = field(default_factory=ProblemConfig)

    def __post_init__(self) -> None:
        check_fields(self)  # a problem mapping -> ProblemConfig, checked
        if self.n_particles < 2:
            raise ConfigError("n_particles", "an int >= 2", self.n_particles)
        if not self.temperature > 0:
            raise ConfigError("temperature", "a finite number > 0", self.temperature)
        if not self.noise_gain > 0:
            raise ConfigError("noise_gain", "a finite number > 0", self.noise_gain)
        if not self.control_cost >= 0:
            raise ConfigError("control_cost", "a finite number >= 0", self.control_cost)
        if self.seed < 0:
            raise ConfigError("seed", "an int >= 0", self.seed)


class _SeededMPPI(MPPI):
    """``pytorch_mppi.MPPI`` whose noise comes from ``generator`` instead of the global torch RNG, and whose
    control cost ``lambda U' Sigma^-1 eps`` is scaled by ``control_cost`` (1: the library's).

    Overrides ``_sample_noise`` of pytorch_mppi 0.9.1 (the only place it draws) and wraps the action-cost
    function it resolves at construction; the rest is the library's.
    """

    def __init__(self, generator: torch.Generator, control_cost: float, *args, **kwargs):
        self.generator = generator  # before MPPI.__init__, which may sample an initial sequence
        super().__init__(*args, **kwargs)
        library_cost = self._compute_action_cost
        self._compute_action_cost = lambda noise: control_cost * library_cost(noise)

    def _sample_noise(self, shape):
        z = torch.randn(*shape, self.nu, generator=self.generator, device=self.d, dtype=self.dtype)
        if self._diagonal_sigma:
            return z * self._noise_sigma_sqrt_diag + self.noise_mu
        return z @ self._noise_sigma_chol.T + self.noise_mu


def generator_seed(seed: int) -> int:
    """The torch generator's seed for the planner seed ``seed`` (an int >= 0 of any size; ``ValueError``
    otherwise, as :class:`bimp.planners.enkts.EnKTSPlanner` refuses it). torch's CPU generator keeps only the low 32
    bits of what ``manual_seed`` gets (its Mersenne Twister takes a 32-bit seed), so seeds that differ only above
    them would draw the same noise: the whole seed goes through ``numpy.random.SeedSequence`` into 32 bits."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be an int >= 0, got {seed!r}")
    return int(np.random.SeedSequence(int(seed)).generate_state(1, np.uint32)[0])


@dataclass(frozen=True)
class _Context:
    """What the running cost of one plan needs beside the block: see :func:`bimp.planners.problem.measure`."""

    problem: Problem
    u_prev: np.ndarray
    ref_lane: np.ndarray
    v_ref: np.ndarray
    a_ref: np.ndarray
    obstacles: tuple[np.ndarray, ...]
    ref_course: np.ndarray


class MPPIPlanner:
    """MPPI as an :class:`bimp.agents.Policy`.

    scene: a :class:`bimp.envs.Scene` or a callable returning the current one (``lambda: env.unwrapped.scene``);
    config: MPPI's settings and problem (noise scales, barriers, horizon); dynamics:
    any batched numpy ``f(x (N, 4), u (N, 2)) -> (N, 4)`` (default: the model ``config.problem.dynamics`` names, as
    EnKTS: the shipped MLP, the bicycle model or a weights file).

    ``fallbacks`` counts plans that came out non-finite and were replaced by holding the last input;
    ``step_info`` says what the last ``act`` did, ``{"fallback": bool}`` (the episode loop records it per step).
    """

    def __init__(self, scene: Scene | Callable[[], Scene], config: MPPIConfig = MPPIConfig(),
                 dynamics: Dynamics | None = None):
        self.config = config
        self.n_particles, self.horizon = config.n_particles, config.problem.horizon
        self._scene = scene if callable(scene) else (lambda: scene)
        built = self._scene()  # the scene at build: what the road asks of the planner
        # The weights by content (in the config's hash) and by name; a model handed in directly is the caller's.
        bound = steer_bound(built)  # the model must cover the road's steering bound
        self.files, self.artifacts = dynamics_files(config.problem.dynamics, bound) if dynamics is None else ({}, {})
        # what the road changes in the problem, for the record
        self.road = road_changes(config.problem, bound, leads(built))
        if dynamics is None:
            dynamics = model_from_name(config.problem.dynamics, bound)
        self.dynamics = dynamics
        self.generator = torch.Generator()
        sigma_du = for_road(config.problem, bound).sigma_du  # the road's steering scale (as the cost's, make_problem)
        noise_std = config.noise_gain * torch.tensor(sigma_du, dtype=torch.float64)
        self._mppi = _SeededMPPI(
            self.generator, config.control_cost, self._step, self.running_cost, nx=NX,
            noise_sigma=torch.diag(noise_std**2),
            num_samples=self.n_particles, horizon=self.horizon, lambda_=config.temperature,
            U_init=torch.zeros(self.horizon, 2, dtype=torch.float64), step_dependent_dynamics=True)
        self._context: _Context | None = None
        self.fallbacks = 0
        self.reset(config.seed)

    def reset(self, seed: int | None = None) -> None:
        """Start a new episode: reseed the generator from the whole ``seed`` (an int >= 0, as EnKTS takes; else
        ``ValueError``), forget the warm start."""
        self.generator.manual_seed(generator_seed(self.config.seed if seed is None else seed))
        self._warm = False
        self.step_info: dict = {}

    # --- Policy ------------------------------------------------------------------------------------------
    def act(self, obs: np.ndarray) -> np.ndarray:
        """Normalized action ``(2,)`` float32 in [-1, 1]: the first control of the updated nominal sequence.

        Raises ``ValueError`` on an observation of the wrong shape or dtype (real numbers only) or with non-finite
        entries.
        """
        scene = self._scene()
        ego, u_prev, ovs, ref = scene.split_obs(scene.check_obs(obs))
        lo, hi = scene.actuator_range
        mppi = self._mppi
        increments = self.config.sample == "increments"
        if increments:  # the rate bounds, tightened as the barriers tighten them
            keep = 1 - self.config.problem.barrier.bound_margin
            rate = np.array([scene.bounds.accel_rate, scene.bounds.steer_rate]) * keep
            mppi.u_min, mppi.u_max = torch.from_numpy(-rate), torch.from_numpy(rate)
        else:
            mppi.u_min, mppi.u_max = torch.from_numpy(lo), torch.from_numpy(hi)
        # The nominal an episode starts from, and falls back to: hold the last input.
        hold = torch.zeros(self.horizon, 2, dtype=torch.float64) if increments else \
            torch.from_numpy(np.tile(u_prev, (self.horizon, 1)))
        if not self._warm:
            mppi.U = hold
        problem = make_problem(scene, self.config.problem, ego_xy=ego[:2])
        v_ref, a_ref, lane, course = reference_profile(problem, ref, ego, self.horizon)
        self._context = _Context(problem, u_prev, lane, v_ref, a_ref,
                                 predict_obstacles(problem, ovs, self.horizon), course)
        start = torch.from_numpy(np.concatenate([ego, u_prev, np.zeros(2), u_prev]))
        # MPPI's own shift refills with a fixed u_init; shift ourselves afterwards (hold the last input).
        u = mppi.command(start, shift_nominal_trajectory=False).numpy().copy()
        if increments:
            u = u_prev + u
        fallback = not (np.all(np.isfinite(u)) and torch.isfinite(mppi.U).all())
        if fallback:
            self.fallbacks += 1
            u = u_prev
            mppi.U = hold
        self.step_info = {"fallback": fallback}
        last = torch.zeros(1, 2, dtype=torch.float64) if increments else mppi.U[-1:]
        mppi.U = torch.cat([mppi.U[1:], last])
        self._warm = True
        return scene.to_normalized(np.clip(u, lo, hi)).astype(np.float32)

    # --- MPPI callbacks ----------------------------------------------------------------------------------
    def _step(self, block: torch.Tensor, action: torch.Tensor, t: int) -> torch.Tensor:
        """Virtual-system transition ``(N, 10) -> (N, 10)`` with MPPI's action ``(N, 2)`` at step ``t`` (eq. 7):
        the state reached with the input ``u`` (the action, or the last input plus the action as an increment,
        within the actuator range), the input, its increment, the first input."""
        b, u = block.numpy(), action.numpy()
        if self.config.sample == "increments":
            u = np.clip(b[:, 4:6] + u, *self._scene().actuator_range)
        x = self.dynamics(b[:, :4], u)
        first = u if t == 0 else b[:, 8:10]
        return torch.from_numpy(np.concatenate([x, u, u - b[:, 4:6], first], axis=1))

    def running_cost(self, block: torch.Tensor, u: torch.Tensor, t: int) -> torch.Tensor:
        """Negative log-likelihood ``(N,)`` of the zero virtual observation at step ``t`` for blocks ``(N, 10)``
        holding ``x_{t+1}`` and the input ``u_t`` that reached it: ``0.5 * sum_i (h_i / sigma_i)^2`` with ``h`` =
        :func:`bimp.planners.problem.measure` and ``sigma`` the problem's measurement noise."""
        ctx = self._context
        b = block.numpy()
        s_o, l_o, v_o, a_o, present = ctx.obstacles
        h = measure(ctx.problem, b[:, :4], b[:, 4:6], b[:, 6:8], b[:, 8:10], ctx.u_prev, ctx.ref_lane[t + 1],
                    ctx.v_ref[t + 1], ctx.a_ref[t + 1], (s_o[t + 1], l_o[t + 1], v_o[t + 1], a_o[t + 1], present),
                    ctx.ref_course[t + 1])
        return torch.from_numpy(0.5 * np.sum((h / ctx.problem.noise) ** 2, axis=1))


def make_mppi(env, config: str | None = None, **overrides) -> MPPIPlanner:
    """MPPI for ``env``, configured in layers (:func:`bimp.planners.problem.load_planner_config`): the shared
    problem (``configs/problem.yaml``) as ``problem`` and :class:`MPPIConfig`'s defaults, the YAML ``config`` on top
    if given (a file of overrides: a key it leaves out keeps its default), then ``overrides`` (``problem=`` a
    mapping merged key by key; an unknown key raises naming it). ``bimp.agents.make_policy("mppi", ...)`` starts
    from the shipped tuned config (``configs/tuned/mppi.yaml``) instead."""
    return MPPIPlanner(lambda: env.unwrapped.scene, load_planner_config(MPPIConfig, config, overrides))


def search_space() -> dict:
    """What ``bimp tune`` searches for MPPI: its temperature, sampling noise and control cost, and the weights and
    margins of its cost (``problem.*``). N is not tuned."""
    from optuna.distributions import FloatDistribution as Float

    # The increments' noise is noise_gain's to set; the barriers' noise is a cost weight here, searched wider.
    shared = {k: v for k, v in problem_search_space().items() if not k.startswith("problem.sigma_du")}
    return {
        "temperature": Float(0.01, 100.0, log=True),
        "noise_gain": Float(0.3, 10.0, log=True),
        "control_cost": Float(0.0, 1.0),
        "problem.sigma_barrier": Float(0.03, 3.0, log=True),
        **shared,
    }


__all__ = ["MPPIConfig", "MPPIPlanner", "generator_seed", "make_mppi", "search_space"]
