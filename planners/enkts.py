"""EnKTS: motion planning by single-pass Student's-t ensemble Kalman smoothing (paper Algorithm 1).

EnKS is the same planner with ``nu = inf`` (Gaussian draws, no spread adaptation): a special case, not a copy.

Per control step the planner smooths the virtual system of :mod:`planners.virtual` over the horizon:

    for t = 0 .. H-1:
        du_t^j = du_nominal_t + w^j,   w ~ St(0, diag(sigma_du^2), nu)          (eq. 7, prediction)
        u_t^j  = u_{t-1}^j + du_t^j;   x_t^j = f(x_{t-1}^j, u_{t-1}^j)
        Y^j    = h(x_t^j, u_t^j, du_t^j) + v^j,  v ~ St(0, R, nu)               (eq. 14)
        [x_t, du_t, u_0..u_t]^j <- student_t_update(..., Y, 0, nu)            (eq. 16-19)

The update reaches back over the whole stored plan (smoothing), but only what later steps or the output
need is stored: the current state and increment, and the controls ``u_0 .. u_t`` (past positions are not
needed to predict the future). The applied action is the smoothed ensemble mean of ``u_0``; the next plan
is warm-started from this plan's mean controls, shifted by one step.

Cost: each horizon step does O(N) model work and an update on a ``(N, 6 + 2(t+1))`` ensemble, so a plan is
linear in N and quadratic in H (the smoothed control history grows with t).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from configs import ConfigError, check_fields, load_config
from envs.scene import Scene
from planners.smoother import student_t, student_t_update
from planners.virtual import N_TRACK, BarrierShape, measure, n_measurements, predict_obstacles, reference_profile

Dynamics = Callable[[np.ndarray, np.ndarray], np.ndarray]
_ACTIVE = 1e-3  # a barrier value below this for every particle counts as not touched
DYNAMICS_NAMES = ("mlp", "bicycle")


@dataclass(frozen=True)
class EnKTSConfig:
    """Planner settings. Units: m, rad, s, m/s, m/s^2; per-step increments are per control step (dt).

    n_particles: ensemble size N >= 2; horizon: H >= 1 steps; nu: degrees of freedom > 2 of the joint
    Student's-t approximation and of the process / measurement noise (``inf``: EnKS); adapt_spread: rescale
    the posterior anomalies by the Student's-t factor; grow_nu: ``nu <- nu + m`` after each update (eq. 19);
    max_spread: cap on that factor (``inf``: none); max_innovation: how many predicted standard deviations the
    virtual observation may lie from the predicted mean, per row and step (see ``_target``); relaxation: share of
    the spread an update removed that is given back (0 = none, see ``_relax``); iterations: smoothing passes per
    step (1 = the paper's single pass);
    sigma_du: process noise scale of ``[da, ddelta]`` per step; sigma_ref: measurement noise of the reference
    state ``[lateral, heading, speed]``; sigma_input: of the reference input ``[a, delta]``; sigma_barrier: of
    each barrier value (the barriers' tightness); barrier: margins and widths; dynamics: ``"mlp"`` (shipped
    model), ``"bicycle"`` (exact model) or the path of a weights file written by ``bimp train-dynamics`` (relative
    to the working directory; checked when the config is built); seed: default seed of the planner's generator.
    Values are checked by :func:`configs.check_fields` (types, lengths) and then for range: a bad one raises
    :class:`configs.ConfigError` naming the key and the value.
    """

    n_particles: int = 50
    horizon: int = 20
    nu: float = 4.0
    adapt_spread: bool = True
    grow_nu: bool = True
    max_spread: float = 25.0
    max_innovation: float = 2.0
    relaxation: float = 0.5
    iterations: int = 1
    sigma_du: tuple[float, float] = (0.5, 0.002)
    sigma_ref: tuple[float, float, float] = (1.0, 0.05, 2.0)
    sigma_input: tuple[float, float] = (3.0, 0.02)
    sigma_barrier: float = 0.1
    barrier: BarrierShape = field(default_factory=BarrierShape)
    dynamics: str = "mlp"
    seed: int = 0

    def __post_init__(self) -> None:
        check_fields(self, allow_inf=("nu", "max_spread"))  # types, lengths; a barrier mapping -> BarrierShape
        if self.n_particles < 2:
            raise ConfigError("n_particles", "an int >= 2", self.n_particles)
        if self.horizon < 1:
            raise ConfigError("horizon", "an int >= 1", self.horizon)
        if not self.nu > 2:
            raise ConfigError("nu", "> 2 (inf for EnKS)", self.nu)
        if self.iterations < 1:
            raise ConfigError("iterations", "an int >= 1", self.iterations)
        if not self.max_spread >= 1:
            raise ConfigError("max_spread", ">= 1 (inf: no cap)", self.max_spread)
        if not self.max_innovation > 0:
            raise ConfigError("max_innovation", "> 0", self.max_innovation)
        if not 0 <= self.relaxation < 1:
            raise ConfigError("relaxation", "in [0, 1)", self.relaxation)
        for key in ("sigma_du", "sigma_ref", "sigma_input", "sigma_barrier"):
            value = getattr(self, key)
            if min(np.atleast_1d(value)) <= 0:
                raise ConfigError(key, "> 0" if key == "sigma_barrier" else "a list of numbers > 0", value)
        check_dynamics(self.dynamics)


def check_dynamics(name: str, key: str = "dynamics") -> None:
    """Raise :class:`configs.ConfigError` unless ``name`` is ``"mlp"``, ``"bicycle"`` or the path of a readable
    weights file written by ``bimp train-dynamics`` (the file is loaded once here, so a bad path fails when the
    config is built, not at the first action)."""
    if name in DYNAMICS_NAMES:
        return
    from planners.dynamics import load_model

    requirement = "'mlp', 'bicycle' or the path of a weights file written by `bimp train-dynamics`"
    try:
        load_model(name)
    except FileNotFoundError:
        raise ConfigError(key, requirement, name, f"no such file: {Path(name).resolve()}") from None
    except ValueError as err:
        raise ConfigError(key, requirement, name, str(err)) from None


@dataclass(frozen=True)
class Plan:
    """The latest plan: ``controls (H, 2)`` smoothed mean ``[a, delta]``, ``states (H + 1, 4)`` rolled out from
    the current state with those controls, ``control_particles (N, H, 2)`` the smoothed ensemble."""

    states: np.ndarray
    controls: np.ndarray
    control_particles: np.ndarray


class EnKTSPlanner:
    """EnKTS (``nu < inf``) or EnKS (``nu = inf``) as a :class:`agents.Policy`.

    scene: a :class:`envs.Scene` or a callable returning the current one (``lambda: env.unwrapped.scene``:
    the road is redrawn at every env reset); dynamics: any batched ``f(x (N, 4), u (N, 2)) -> (N, 4)``, by
    default the one ``config.dynamics`` names.
    """

    def __init__(self, scene: Scene | Callable[[], Scene], config: EnKTSConfig = EnKTSConfig(),
                 dynamics: Dynamics | None = None):
        self.config = config
        self._scene = scene if callable(scene) else (lambda: scene)
        self.dynamics = dynamics or _default_dynamics(config.dynamics)
        self.fallbacks = 0  # plans that came out non-finite and were replaced by holding the last input
        self.reset(config.seed)

    def reset(self, seed: int | None = None) -> None:
        """Start a new episode: reseed the generator, forget the warm start."""
        self.rng = np.random.default_rng(self.config.seed if seed is None else seed)
        self._previous: np.ndarray | None = None
        self._last: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    # --- Policy ------------------------------------------------------------------------------------
    def act(self, obs: np.ndarray) -> np.ndarray:
        """Normalized action ``(2,)`` float32 in [-1, 1]: the smoothed mean of the first control.

        Raises ``ValueError`` on an observation of the wrong shape or with non-finite entries.
        """
        scene = self._scene()
        ego, u_prev, ovs, ref = scene.split_obs(scene.check_obs(obs))
        cfg = self.config
        nominal = self._warm_start(u_prev)
        obstacles = predict_obstacles(scene, ovs, cfg.horizon)
        v_ref, a_ref = reference_profile(scene, ref, cfg.horizon)
        for _ in range(cfg.iterations):
            U = self._smooth(scene, ego, u_prev, nominal, obstacles, ref[2], v_ref, a_ref)
            nominal = U.mean(axis=0)
        controls = nominal
        if not np.all(np.isfinite(controls)):
            self.fallbacks += 1
            controls = np.tile(u_prev, (cfg.horizon, 1))
            U = np.broadcast_to(controls, U.shape)
        controls = np.clip(controls, *scene.actuator_range)
        self._previous = controls
        self._last = (ego, controls, U)
        return scene.to_normalized(controls[0]).astype(np.float32)

    @property
    def plan(self) -> Plan | None:
        """The latest plan (``None`` before the first ``act``); states are rolled out on demand."""
        if self._last is None:
            return None
        ego, controls, U = self._last
        states = [ego]
        for u in controls:
            states.append(self.dynamics(states[-1][None], u[None])[0])
        return Plan(states=np.array(states), controls=controls.copy(), control_particles=np.array(U))

    # --- internals ---------------------------------------------------------------------------------
    def _warm_start(self, u_prev: np.ndarray) -> np.ndarray:
        """Nominal controls ``(H, 2)``: the previous plan shifted by one step, or holding ``u_prev``."""
        if self._previous is None:
            return np.tile(u_prev, (self.config.horizon, 1))
        return np.vstack([self._previous[1:], self._previous[-1:]])

    def _target(self, Y: np.ndarray) -> np.ndarray:
        """The virtual observation ``(m,)``: zeros, moved to within ``max_innovation`` standard deviations of the
        predicted mean ``Y (N, m)``.

        A barrier deep in violation that the ensemble can barely move (a gap no braking closes in one step)
        would otherwise be an innovation of tens of sigmas, and the linear update would extrapolate the
        regression far outside the ensemble: controls of -12 m/s^2 from a spread of 0.5. Asking per step only
        for what the ensemble can reach bounds every shift, and the surprise still widens the spread (delta).
        """
        mean, std = _mean_std(Y)
        reach = self.config.max_innovation * std
        return np.clip(0.0, mean - reach, mean + reach)

    def _relax(self, Z: np.ndarray, prior_std: np.ndarray) -> None:
        """Relaxation to the prior spread (Whitaker & Hamill 2012), in place: each column's posterior spread
        moves back by ``relaxation`` towards its prior spread.

        With N = 50 and about ten measurement rows, each update also removes ~m/N of every column's variance
        through spurious sample correlations; over 20 steps the first control (the one applied) would keep
        a few percent of its spread, and a danger that only shows late in the horizon could no longer move it.
        """
        mean, post_std = _mean_std(Z)
        alpha = self.config.relaxation
        scale = np.where(post_std > 0, 1.0 + alpha * (prior_std / np.maximum(post_std, 1e-12) - 1.0), 1.0)
        Z[:] = mean + (Z - mean) * np.maximum(scale, 1.0)

    def _smooth(self, scene: Scene, ego: np.ndarray, u_prev: np.ndarray, nominal: np.ndarray,
                obstacles: tuple, ref_lane: float, v_ref: np.ndarray, a_ref: np.ndarray) -> np.ndarray:
        """One smoothing pass; returns the smoothed control particles ``(N, H, 2)``."""
        cfg = self.config
        n, horizon = cfg.n_particles, cfg.horizon
        s_o, l_o, v_o, a_o, present = obstacles
        m = n_measurements(len(present))
        noise_scale = np.array([*cfg.sigma_ref, *cfg.sigma_input] + [cfg.sigma_barrier] * (m - N_TRACK))
        du_nominal = np.diff(np.vstack([u_prev, nominal]), axis=0)
        nu = cfg.nu
        x = np.tile(ego, (n, 1))
        u_last = np.tile(u_prev, (n, 1))
        Z = np.empty((n, 6 + 2 * horizon))  # [x (4), du (2), u_0 .. u_{H-1}]
        for t in range(horizon):
            if t > 0:
                x = self.dynamics(x, u_last)
            du = du_nominal[t] + student_t(self.rng, cfg.sigma_du, cfg.nu, n)
            u_last = u_last + du
            width = 8 + 2 * t
            Z[:, :4], Z[:, 4:6], Z[:, width - 2:width] = x, du, u_last
            h = measure(scene, cfg.barrier, x, u_last, du, Z[:, 6:8], u_prev, ref_lane, v_ref[t], a_ref[t],
                        (s_o[t], l_o[t], v_o[t], a_o[t], present))
            Y = h + student_t(self.rng, noise_scale, cfg.nu, n)
            # A barrier that reads ~0 for every particle is flat there and carries no information, yet with
            # N = 50 its noise regresses spuriously on the plan and collapses the ensemble within a few steps:
            # only the tracking rows and the barriers some particle touches enter the update.
            active = np.concatenate([np.ones(N_TRACK, bool), h[:, N_TRACK:].max(axis=0) > _ACTIVE])
            Y = Y[:, active]
            prior_std = _mean_std(Z[:, :width])[1]
            Z[:, :width], nu_post = student_t_update(Z[:, :width], Y, self._target(Y), nu,
                                                     adapt_spread=cfg.adapt_spread, max_spread=cfg.max_spread)
            if cfg.relaxation > 0:
                self._relax(Z[:, :width], prior_std)
            if cfg.grow_nu:
                nu = nu_post
            x, u_last = Z[:, :4], Z[:, width - 2:width]
        return Z[:, 6:].reshape(n, horizon, 2)


def _mean_std(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Column means and (population) standard deviations of ``A (N, D)``; np.mean/np.std cost more in their
    Python wrappers than in the arithmetic at N = 50, and this runs several times per horizon step."""
    n = A.shape[0]
    mean = A.sum(axis=0) / n
    centred = A - mean
    return mean, np.sqrt((centred * centred).sum(axis=0) / n)


def _default_dynamics(name: str) -> Dynamics:
    from planners.dynamics import model_from_name

    return model_from_name(name)


CONFIG_FILE = "planner.yaml"


def make_enkts(env, config: str | None = CONFIG_FILE, **overrides) -> EnKTSPlanner:
    """EnKTS for ``env`` with the shared tuning of ``configs/planner.yaml`` plus ``overrides``."""
    return EnKTSPlanner(lambda: env.unwrapped.scene, load_config(EnKTSConfig, config, **overrides))


def make_enks(env, config: str | None = CONFIG_FILE, **overrides) -> EnKTSPlanner:
    """EnKS: the same tuning as EnKTS except ``nu = inf`` (paper: "all other parameters the same")."""
    return make_enkts(env, config, **{"nu": math.inf, **overrides})


__all__ = ["EnKTSConfig", "EnKTSPlanner", "Plan", "make_enkts", "make_enks"]
