"""``paper-noisy`` (issue 27): the paper's two scenarios (:mod:`bimp.envs.scenarios`) with observation noise and a
model mismatch: the world the planners see is noisy, and the EV's dynamics are not the ones their learned model (an
MLP fitted to highway-env's kinematic bicycle, :mod:`bimp.planners.dynamics`) predicts.

Two scenarios, each the paper env with :class:`PaperNoisy` before it in its bases:

- ``overtaking-noisy`` (``bimp/overtaking-noisy-v0``, :class:`NoisyOvertakingEnv`, 15 s): the paper's overtaking
  scenario (``bimp/Overtaking-v0``), its ranges unchanged;
- ``emergency-brake-noisy`` (``bimp/emergency-brake-noisy-v0``, :class:`NoisyEmergencyBrakeEnv`, 12 s): the paper's
  emergency brake (``bimp/EmergencyBrake-v0``) with OV1 22 m further ahead (``ov1_gap`` 72 - 82 m instead of
  50 - 60 m), so that the lagged, low-grip EV of the hard difficulty can still stop clear of it (the oracle, below).

The paper env draws its scenario first, in its own order, then the family draws its ranges: with no noise and no
mismatch an episode is the paper env's of the same seed. What changes, every draw from the env's ``np_random`` (the
ranges per episode at ``reset``, the noise at every observation):

- **observation noise**: the policy's observation of each present OV has independent Gaussian noise of standard
  deviation ``ov_position_noise`` [m] added to its x and y, and ``ov_speed_noise`` [m/s] to its speed. Gaussian: a
  sensor's error is the sum of many small ones, and its tails are what a planner's margins must absorb. The OVs'
  heading and acceleration, the EV's own state and the reference are observed as they are: bimp's records take the
  EV's trajectory from the observation (:mod:`bimp.agents.rollout`), so noise on it would be in every jerk and speed
  metric. The env's own safety info (``collision``, ``ov_distance``, ``ttc``, ``edge_distance``, the score's
  ``contact``) and the overtaking behaviour layer's reference stay on the true state;
- **model mismatch** of the EV (:class:`MismatchedEgoVehicle`): a **longer wheelbase**, ``length_ratio`` times the
  5 m that highway-env's bicycle (and so the planners' MLP) uses in the slip angle's yaw rate
  ``v sin(beta) / (L / 2)``: the same steering turns the EV ``1 / length_ratio`` as fast (the drawn footprint stays
  5 m); a **first-order lag** of time constant ``accel_lag`` [s] between the commanded and the achieved
  acceleration (a powertrain and brake lag); and a **grip** factor, the share of the command the tyres and brakes
  achieve: ``a <- a + (1 - exp(-dt / accel_lag)) (grip a_cmd - a)`` every simulation step, the exact response of
  ``da/dt = (grip a_cmd - a) / accel_lag`` to a command held over the step (``accel_lag`` 0: ``a = grip a_cmd``).

Ranges per ``difficulty`` (:data:`OVERTAKING_DIFFICULTIES`, :data:`EMERGENCY_BRAKE_DIFFICULTIES`; a ``(lo, hi)`` pair
is drawn uniformly per episode, a number fixes it; the noise keys are standard deviations):

============  =================  ==============  ============  ============  =================  ======================
difficulty    ov_position_noise  ov_speed_noise  length_ratio  accel_lag     grip (overtaking)  grip (emergency brake)
============  =================  ==============  ============  ============  =================  ======================
easy          0 - 0.1 m          0 - 0.1 m/s     1 - 1.1       0 - 0.1 s     1                  0.95 - 1
medium        0.1 - 0.3 m        0.1 - 0.3 m/s   1.1 - 1.25    0.1 - 0.25 s  1                  0.9 - 0.95
hard          0.3 - 0.6 m        0.3 - 0.8 m/s   1.25 - 1.5    0.25 - 0.4 s  1                  0.8 - 0.9
============  =================  ==============  ============  ============  =================  ======================

The envelope (:data:`NOISE_PARAMS`): noise standard deviations in [0, 2] (2 m is half a lane); ``length_ratio`` in
[0.7, 1.5] (at 1.5 holding the inner lane of the tightest curve of the overtaking ranges, radius 178 m, takes
0.042 rad of steering, inside the 0.05 rad bound; the overtaking env refuses a ratio and radius whose hold leaves
less than :data:`STEER_HEADROOM`); ``accel_lag`` in [0, 1] s and ``grip`` in [0.5, 1], both further limited by the
oracle.

The oracle: every instance leaves a safe plan inside the planning bounds under the mismatch. The plan is the paper
scenarios' (``tests/envs/test_feasibility.py``): braking at the planning bounds (the command ramps to ``a_min`` by the
rate bound) in the EV's lane, on the emergency brake from the step after the OVs' deceleration shows, on overtaking
from the first step behind OV1 (which never brakes). Under the mismatch the achieved deceleration follows the command
late and short: the shared oracle (:func:`bimp.envs.oracle.braking`, with ``lag`` and ``grip``) simulates it exactly
as :class:`MismatchedEgoVehicle` steps. The worst case of the ranges is among
their corners (fastest EV, nearest and slowest OV1, braking hardest and latest, longest lag, least grip), which
every config is checked on: one whose worst corner leaves less than ``d_min`` is refused naming ``ov1_gap`` (where
even the model's EV fails), ``grip`` (where the full grip would pass) or ``accel_lag``; on overtaking also one whose
stop does not end on the straight before the curve (:data:`STRAIGHT_IN`, naming ``ev_speed``), so that the longer
wheelbase never has to steer it. The plan drives straight on a straight stretch, so the wheelbase does not enter
it. Observation noise cannot break the oracle: the plan is a fact of the world (when to brake is set by the true
onset), not of what a policy sees; a noisy policy may fail where the plan does not, which is the family's point.

Success: the time limit reached without collision or leaving the road, as on the paper's scenarios.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Mapping
from types import MappingProxyType
from typing import ClassVar

import numpy as np
from numpy.typing import ArrayLike

from bimp.configs import ConfigError
from bimp.envs.oracle import NEVER, braking, lag_gain
from bimp.envs.scenarios import (
    LANE_WIDTH,
    MAX_GAP,
    MIN_CENTRE_GAP,
    BimpObservation,
    EgoVehicle,
    EmergencyBrakeEnv,
    OvertakingEnv,
    Param,
)
from bimp.envs.scene import OV_FIELDS, VEHICLE_LENGTH, Bounds, join_obs
from bimp.envs.suite.family import check_fixed_difficulty, with_difficulty

BOUNDS = Bounds()
STRAIGHT_IN = 100.0  # m: the overtaking road's straight before the curve (OvertakingEnv._scene_road)
# rad: the steering the curve's hold may leave below the bound, for the rate-limited feedback that corrects a
# lateral error (0.0075 rad: 1.5 steps of the 0.005 rad/step rate bound)
STEER_HEADROOM = 0.0075
_X, _Y, _SPEED = (OV_FIELDS.index(k) for k in ("x", "y", "speed"))

# The family's keys: each a (lo, hi) range drawn per episode (a number fixes it), inside these envelopes.
NOISE_PARAMS: Mapping[str, Param] = MappingProxyType({
    "ov_position_noise": Param((0.1, 0.3), "std of the Gaussian noise on each observed OV's x and y, m; at most half "
                               "a lane", 0.0, 2.0),
    "ov_speed_noise": Param((0.1, 0.3), "std of the Gaussian noise on each observed OV's speed, m/s", 0.0, 2.0),
    "length_ratio": Param((1.1, 1.25), "the EV's kinematic length over the 5 m its model assumes: the yaw rate per "
                          "steering input scales by its inverse; up to 1.5, where the tightest curve's hold is "
                          "0.042 rad of the 0.05 rad bound", 0.7, 1.5),
    "accel_lag": Param((0.1, 0.25), "time constant of the first-order lag from commanded to achieved "
                       "acceleration, s; 0: none; the oracle limits it further", 0.0, 1.0),
    "grip": Param((1.0, 1.0), "share of the (lagged) commanded acceleration the EV achieves, its tyres' and brakes' "
                  "effectiveness; 1: the model's; the oracle limits it further", 0.5, 1.0),
})


def _presets(grip: Mapping[str, tuple[float, float]]) -> Mapping[str, Mapping[str, tuple[float, float]]]:
    """The difficulties' ranges: the noise, wheelbase and lag the two scenarios share, and ``grip``'s per difficulty."""
    shared = {
        "easy": {"ov_position_noise": (0.0, 0.1), "ov_speed_noise": (0.0, 0.1), "length_ratio": (1.0, 1.1),
                 "accel_lag": (0.0, 0.1)},
        "medium": {"ov_position_noise": (0.1, 0.3), "ov_speed_noise": (0.1, 0.3), "length_ratio": (1.1, 1.25),
                   "accel_lag": (0.1, 0.25)},
        "hard": {"ov_position_noise": (0.3, 0.6), "ov_speed_noise": (0.3, 0.8), "length_ratio": (1.25, 1.5),
                 "accel_lag": (0.25, 0.4)},
    }
    return MappingProxyType({d: MappingProxyType({**ranges, "grip": grip[d]}) for d, ranges in shared.items()})


# Overtaking keeps the model's grip: following OV1 (25 m ahead at 15 m/s, the EV at 27 m/s) leaves 1.97 m with hard's
# 0.4 s lag, and 0.76 m with a grip of 0.9 besides.
OVERTAKING_DIFFICULTIES = _presets({"easy": (1.0, 1.0), "medium": (1.0, 1.0), "hard": (1.0, 1.0)})
# The emergency brake loses grip: what its planners' margins do not absorb (with hard's lag and noise alone, OV1 60-70 m
# ahead, EnKTS, EnKS and MPPI all stopped clear on development seeds 0-9; with hard's grip besides, EnKTS hit OV1 on 2).
EMERGENCY_BRAKE_DIFFICULTIES = _presets({"easy": (0.95, 1.0), "medium": (0.9, 0.95), "hard": (0.8, 0.9)})
DIFFICULTIES = MappingProxyType({"overtaking-noisy": OVERTAKING_DIFFICULTIES,
                                 "emergency-brake-noisy": EMERGENCY_BRAKE_DIFFICULTIES})


def _params(base: Mapping[str, Param], presets: Mapping[str, Mapping[str, tuple[float, float]]],
            **changed: Param) -> dict[str, Param]:
    """A paper env's ``PARAMS`` with ``changed`` and the family's keys, their defaults the ``medium`` presets."""
    return {**base, **changed, **{k: dataclasses.replace(p, default=presets["medium"][k])
                                  for k, p in NOISE_PARAMS.items()}}


def steer_to_hold(radius: ArrayLike, length: ArrayLike) -> np.ndarray:
    """The steering [rad] that holds highway-env's bicycle of kinematic length ``length`` [m] on a circle of
    ``radius`` [m]: yaw rate ``v sin(beta) / (length / 2)`` equal to ``v / radius``, ``beta = atan(tan(delta) / 2)``."""
    beta = np.arcsin(np.asarray(length, float) / (2.0 * np.asarray(radius, float)))
    return np.arctan(2.0 * np.tan(beta))


class MismatchedEgoVehicle(EgoVehicle):
    """The EV whose dynamics are off its model's: highway-env's kinematic bicycle (``Vehicle.step``) with the yaw
    rate of a ``length_ratio`` x 5 m vehicle and the achieved acceleration ``applied_acceleration`` [m/s^2] lagging
    the command through a first-order lag of ``accel_lag`` [s] (module docstring). The speed stays >= 0 as the EV's;
    at ratio 1 and lag 0 it steps exactly as :class:`bimp.envs.scenarios.EgoVehicle`."""

    def __init__(self, *args, length_ratio: float = 1.0, accel_lag: float = 0.0, grip: float = 1.0, **kwargs):
        super().__init__(*args, **kwargs)
        self.length_ratio, self.accel_lag, self.grip = float(length_ratio), float(accel_lag), float(grip)
        self.applied_acceleration = 0.0

    def step(self, dt: float) -> None:
        # Vehicle.step with the two changes; highway-env's impact translation never happens here (no collisions).
        self.clip_actions()
        self.applied_acceleration += float(lag_gain(self.accel_lag, dt)) * \
            (self.grip * self.action["acceleration"] - self.applied_acceleration)
        beta = np.arctan(0.5 * np.tan(self.action["steering"]))
        self.position += self.speed * np.array([np.cos(self.heading + beta), np.sin(self.heading + beta)]) * dt
        self.heading += self.speed * np.sin(beta) / (self.length_ratio * self.LENGTH / 2.0) * dt
        self.speed = max(self.speed + self.applied_acceleration * dt, 0.0)
        self.on_state_update()


class NoisyObservation(BimpObservation):
    """:class:`bimp.envs.scenarios.BimpObservation` with the family's Gaussian noise (module docstring) drawn from the
    env's ``np_random`` at every observation; absent OV rows stay zeros."""

    def observe(self) -> np.ndarray:
        env = self.env
        ego, u_prev, ovs, ref = env.scene.split_obs(super().observe())
        ovs = ovs.copy()
        rng, std = env.np_random, env.noise_std
        present = ovs[:, 0] > 0.5
        n = len(ovs)
        ovs[:, _X] += np.where(present, rng.normal(0.0, std["ov_position_noise"], n), 0.0)
        ovs[:, _Y] += np.where(present, rng.normal(0.0, std["ov_position_noise"], n), 0.0)
        ovs[:, _SPEED] += np.where(present, rng.normal(0.0, std["ov_speed_noise"], n), 0.0)
        return join_obs(ego, u_prev, ovs, ref).astype(np.float32)


_COVERED: set[tuple] = set()  # the configs whose worst corner the oracle has passed, by class and values


class PaperNoisy:
    """The mixin of the family's two envs (bases ``(PaperNoisy, <paper env>)``). The family's interface as
    :class:`bimp.envs.suite.family.Family` has it (``NAME``, ``DIFFICULTIES``, ``DEFAULT_DIFFICULTY``,
    :meth:`range_keys`, ``DURATION``), on the paper envs' own config machinery: the noise and mismatch keys are
    ``PARAMS`` of the env (checked, drawn and recorded in ``drawn_params`` as the scenario's own), ``difficulty`` an
    option that sets all of them at once (a key given beside it overrides its preset; given alone it resets them), and
    the oracle's worst corner checked on every config (``gym.make``'s and every ``reset``'s). Refusals are
    ``ValueError`` naming the key. ``difficulty`` as a constructor argument (the ``-easy``/``-hard`` scenarios'
    registration) refuses a config, at ``gym.make`` or at any reset, that names another."""

    NAME: ClassVar[str] = ""
    DURATION: ClassVar[float] = 0.0  # s
    DIFFICULTIES: ClassVar[Mapping[str, Mapping[str, tuple[float, float]]]] = {}
    DEFAULT_DIFFICULTY: ClassVar[str] = "medium"
    ORACLE_KEYS: ClassVar[tuple[str, ...]] = ()  # the config keys the oracle's check reads
    fixed_difficulty: str | None = None  # the difficulty the id names (bimp/overtaking-noisy-hard-v0), else None
    noise_std: dict[str, float]

    def __init__(self, config: dict | None = None, render_mode: str | None = None,
                 difficulty: str | None = None, fast_traffic: bool = True) -> None:
        super().__init__(config=with_difficulty(self, config, difficulty), render_mode=render_mode,
                         fast_traffic=fast_traffic)

    @classmethod
    def range_keys(cls) -> tuple[str, ...]:
        """The config keys of the family's ranges (noise and mismatch), in :data:`NOISE_PARAMS`' order."""
        return tuple(NOISE_PARAMS)

    def _with_preset(self, overrides: Mapping | None) -> Mapping | None:
        """``overrides`` with the presets of the ``difficulty`` it names under the keys it does not give."""
        if not isinstance(overrides, Mapping) or "difficulty" not in overrides:
            return overrides
        difficulty = overrides["difficulty"]
        check_fixed_difficulty(self, difficulty)
        if not isinstance(difficulty, str) or difficulty not in self.DIFFICULTIES:
            raise ConfigError("difficulty", f"one of {', '.join(map(repr, self.DIFFICULTIES))}", difficulty,
                              f"the difficulties {self.NAME}'s oracle covers")
        return {**self.DIFFICULTIES[difficulty], **overrides}

    def configure(self, config: Mapping | None) -> None:
        # The paper env stores only the keys given: a difficulty given alone must bring its presets with it.
        super().configure(self._with_preset(config))

    def _checked_config(self, base: dict, overrides: Mapping | None) -> dict:
        config = super()._checked_config(base, self._with_preset(overrides))
        # Every reset checks its config; the oracle's simulation (60 ms) runs once per set of values.
        key = (type(self).__name__, *((k, config[k]) for k in self.ORACLE_KEYS))
        if key not in _COVERED:
            self._check_oracle(config)
            _COVERED.add(key)
        return config

    def _check_oracle(self, config: dict) -> None:
        """``ValueError`` naming the key when the config's worst corner leaves the oracle's cover."""
        raise NotImplementedError

    def _reset(self) -> None:
        super()._reset()  # the paper env's draws first, in its order: the scenario is the paper's
        self.noise_std = {k: self._draw(k) for k in ("ov_position_noise", "ov_speed_noise")}
        ratio, lag, grip = self._draw("length_ratio"), self._draw("accel_lag"), self._draw("grip")
        old = self.vehicle
        ev = MismatchedEgoVehicle(self.road, old.position, old.heading, old.speed, length_ratio=ratio, accel_lag=lag,
                                  grip=grip)
        ev.color = old.color
        self.road.vehicles[self.road.vehicles.index(old)] = ev
        self.vehicle = ev

    def define_spaces(self) -> None:
        super().define_spaces()
        self.observation_type = NoisyObservation(self)


def _corners(config: dict, keys: tuple[str, ...]) -> list[dict]:
    """Every corner of ``config``'s ranges of ``keys`` (a fixed number is its own corner)."""
    values = [config[k] if isinstance(config[k], tuple) else (config[k],) for k in keys]
    return [dict(zip(keys, c)) for c in itertools.product(*values)]


STOP_STEPS = 250  # the oracle's steps of 0.1 s: 25 s cover the stop from 40 m/s at half the grip and a 1 s lag


def _check_braking(config: dict, scenario_keys: tuple[str, ...], what: str, **fixed) -> np.ndarray:
    """The oracle's braking (:func:`bimp.envs.oracle.braking`, its first arguments ``scenario_keys`` of ``config``,
    ``fixed`` the rest) on every corner of the ranges of ``scenario_keys``, ``accel_lag`` and ``grip``:
    ``ConfigError`` when the worst leaves less than ``d_min``, naming the scenario's gap where even the model's EV
    (no lag, full grip) fails there, else ``grip`` where the full grip would pass, else ``accel_lag``. Returns the
    distances travelled [m] per corner."""
    keys = (*scenario_keys, "accel_lag", "grip")
    rows = _corners(config, keys)
    column = {k: np.array([c[k] for c in rows]) for k in keys}
    fixed = {"steps": STOP_STEPS, **fixed}
    gaps, travel = braking(*(column[k] for k in scenario_keys), lag=column["accel_lag"], grip=column["grip"],
                           **fixed)
    i = int(np.argmin(gaps))
    if gaps[i] >= BOUNDS.d_min:
        return travel
    worst = rows[i]
    shown = ", ".join(f"{k}={worst[k]:g}" for k in keys)
    model = float(braking(*(worst[k] for k in scenario_keys), lag=0.0, grip=1.0, **fixed)[0])
    full_grip = float(braking(*(worst[k] for k in scenario_keys), lag=worst["accel_lag"], grip=1.0, **fixed)[0])
    key = "ov1_gap" if model < BOUNDS.d_min else "grip" if full_grip >= BOUNDS.d_min else "accel_lag"
    raise ConfigError(key, "a range the oracle covers" + (" even for the model's EV (no lag, full grip)"
                                                          if key == "ov1_gap" else ""), config[key],
                      f"{what} at the worst corner ({shown}) leaves {float(gaps[i]):.2f} m (the model's EV "
                      f"{model:.2f} m), d_min is {BOUNDS.d_min:g} m")


class NoisyOvertakingEnv(PaperNoisy, OvertakingEnv):
    """``overtaking-noisy``: :class:`bimp.envs.scenarios.OvertakingEnv` with the family's observation noise and EV
    mismatch (module docstring). Oracle: braking at the bounds from the first step stops at least ``d_min`` behind
    OV1 and on the straight, under the longest lag and the least grip; the curve's hold takes at most the steering
    bound less :data:`STEER_HEADROOM` at the longest length."""

    NAME = "overtaking-noisy"
    DURATION = 15.0
    DIFFICULTIES = OVERTAKING_DIFFICULTIES
    PARAMS = _params(OvertakingEnv.PARAMS, OVERTAKING_DIFFICULTIES)
    OPTIONS = {**OvertakingEnv.OPTIONS, "difficulty": ("medium", "easy", "hard")}
    ORACLE_KEYS = ("ev_speed", "ov1_gap", "ov1_speed", "accel_lag", "grip", "radius", "length_ratio")

    def _check_oracle(self, config: dict) -> None:
        travel = _check_braking(config, ("ev_speed", "ov1_gap", "ov1_speed"), "braking at the bounds behind OV1",
                                onset=NEVER, decel=0.0, react=False)
        far = float(travel.max()) + VEHICLE_LENGTH / 2.0  # the EV's front at its stop, from its start at 0
        if far > STRAIGHT_IN:
            raise ConfigError("ev_speed", "a range whose stop ends on the straight", config["ev_speed"],
                              f"braking at the bounds with the ranges' longest lag and least grip ends {far:.1f} m "
                              f"along the road (the EV's front), past the {STRAIGHT_IN:g} m straight before the curve")
        radius = min(np.atleast_1d(config["radius"])) - LANE_WIDTH / 2.0  # the inner lane of the tightest curve
        length = max(np.atleast_1d(config["length_ratio"])) * VEHICLE_LENGTH
        hold = float(steer_to_hold(radius, length))
        if hold > BOUNDS.steer - STEER_HEADROOM:
            raise ConfigError("length_ratio", "a range whose longest EV holds the tightest curve within the steering "
                              f"bound less {STEER_HEADROOM:g} rad", config["length_ratio"],
                              f"holding radius {radius:g} m at {length:g} m takes {hold:.4f} rad, the bound is "
                              f"{BOUNDS.steer:g} rad")


class NoisyEmergencyBrakeEnv(PaperNoisy, EmergencyBrakeEnv):
    """``emergency-brake-noisy``: :class:`bimp.envs.scenarios.EmergencyBrakeEnv` with OV1 22 m further ahead
    (``ov1_gap`` 72 - 82 m) and the family's observation noise and EV mismatch (module docstring). Oracle: braking at
    the bounds from the step after the OVs' deceleration shows stops at least ``d_min`` behind OV1 under the longest
    lag and the least grip, on every corner of the ranges."""

    NAME = "emergency-brake-noisy"
    DURATION = 12.0
    DIFFICULTIES = EMERGENCY_BRAKE_DIFFICULTIES
    # 22 m more than the paper's 50 - 60 m: hard's worst corner (27 m/s, OV1 at 20 m/s braking at 7 m/s^2 from 1.2 s,
    # a lag of 0.4 s and a grip of 0.8) stops 2.0 m clear from 72 m; the paper's 50 m leaves 2.1 m to the model's EV.
    PARAMS = _params(EmergencyBrakeEnv.PARAMS, EMERGENCY_BRAKE_DIFFICULTIES,
                     ov1_gap=Param((72.0, 82.0), "centre gap of OV1 (EV's lane) ahead of the EV, m", MIN_CENTRE_GAP,
                                   MAX_GAP))
    OPTIONS = {**EmergencyBrakeEnv.OPTIONS, "difficulty": ("medium", "easy", "hard")}
    ORACLE_KEYS = ("ev_speed", "ov1_gap", "ov_speed", "brake_onset", "brake_decel", "accel_lag", "grip")

    def _check_oracle(self, config: dict) -> None:
        _check_braking(config, self.ORACLE_KEYS[:5], "braking at the bounds once OV1's deceleration shows")


FAMILY: tuple[type[PaperNoisy], ...] = (NoisyOvertakingEnv, NoisyEmergencyBrakeEnv)

__all__ = ["DIFFICULTIES", "EMERGENCY_BRAKE_DIFFICULTIES", "FAMILY", "NOISE_PARAMS", "OVERTAKING_DIFFICULTIES",
           "MismatchedEgoVehicle", "NoisyEmergencyBrakeEnv", "NoisyObservation", "NoisyOvertakingEnv", "PaperNoisy",
           "lag_gain", "steer_to_hold"]
