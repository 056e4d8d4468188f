"""The paper's two scenarios (section V) as highway-env environments.

Both share :class:`BimpEnv`: a two-lane road of 4 m lanes, dt = 0.1 s (simulation and policy frequency
10 Hz), the EV driven by a continuous ``[acceleration, steering]`` action in [-1, 1] that maps linearly
onto actuator ranges wider than the planning bounds (so violations of the bounds are measurable).
**Actions outside [-1, 1] are clipped; a non-finite action, or one that is not real numbers (a string, a complex
number, a bool), raises ValueError** (:func:`bimp.envs.checks.checked_action`). Speeds never go negative.

Configuration: ``gym.make(id, config={...})`` sets the base configuration. Scenario parameters (``PARAMS`` of
each env, listed with units and accepted values in its docstring) given as a 2-sequence ``(lo, hi)`` are drawn
uniformly from ``self.np_random`` at every ``reset``; a number fixes them. ``reset(options={"config": {...}})``
overrides the configuration *for that episode only* (Gymnasium's convention; highway-env would keep it): the next
plain ``reset()`` is back on the ``gym.make`` config. Both are validated before anything is simulated, and every
error is a ``ValueError`` naming the key and the value: an unknown key; a value that is not a finite real number or
a ``(lo, hi)`` pair of them with ``lo <= hi`` (bools, strings, NaN, inf, other lengths are refused); a value outside
the parameter's interval (speeds in [0, 40] m/s, gaps >= one vehicle length + d_min = 6 m between centres so
the vehicles start clear of each other and of the distance constraint, and <= ``MAX_GAP`` = 1 km so every position
stays inside the observation space, ``brake_decel`` a magnitude > 0, ...);
and orders that must hold for the worst case of the ranges, not only for one draw (OV2 ahead of OV1, the
reference's ``ref_zero_step`` after ``ref_hold``). highway-env's own keys (rendering) pass through, checked as the
adapter checks them (:func:`bimp.envs.checks.check_highway_config`); ``policy_frequency`` must be 10 Hz (the planners
plan at dt = 0.1 s) and ``action`` is refused (the EV is driven by the env's own continuous action).

Collision: ``info["collision"]`` is true exactly when the EV's footprint touches or overlaps an OV's, i.e. when
``min(info["ov_distance"]) <= 0``, the exact signed distance between the two 5 m x 2 m rectangles
(:meth:`bimp.envs.scene.Scene.ov_gaps`). It is measured on the simulated state itself: highway-env's collision handling
(which predicts an intersection one step ahead, pushes both vehicles apart by an "impact" translation and then
brakes crashed vehicles to a stop) is switched off for all vehicles, so no contact moves anyone, OV-OV contacts
included. The env checks the gap after every simulation step and ends the step at the first overlapping state.
The EV and the OVs it touches are marked ``crashed`` only so that highway-env draws them so.

Rendering: ``metadata["render_fps"]`` is the policy frequency, one frame per step as gymnasium's ``RecordVideo``
captures them, so videos play in real time (highway-env would double it, in a dict shared by all instances).
It is set per instance at every reset; ``RecordVideo`` reads it once, when it wraps the env.

Observation (flat ``Box``, float32, see :mod:`bimp.envs.scene`): EV ``[x, y, heading, speed]``, the previous
physical input ``[a, delta]``, per OV ``[present, x, y, heading, speed, acceleration]``, and the reference
``[v_ref, dv_ref/dt, lateral offset of the reference lane]``.

``info`` per step: ``collision``, ``offroad`` (any body corner past a road edge), ``ov_distance`` (signed
footprint gap to each OV, see above), ``edge_distance`` (least corner distance to the edge), ``ttc`` (time to
collision with the nearest closing OV in the EV's lane), ``reference``, ``lateral_error``, ``speed_error``,
``input`` (the physical input applied), ``constraints`` (paper eq. 2-5 as values that are <= 0 when satisfied; the
input and rate ones are :func:`bimp.envs.scene.bound_constraints`, the very function the planners' barriers measure),
and for the closed-loop score (:func:`bimp.envs.scene.attribution_info`, ``docs/suite.md``) ``contact`` (None, or
the OV in contact in the EV's body frame with both speeds and the EV's lateral speed across the road) and
``speed_limit`` (the cruise speed, the EV's initial speed: the road has no limit of its own).

Reward (for RL): tracking of the reference speed measured *along the road* and of the reference lane,
in [0, 1] per step, minus small penalties for inputs and rate beyond the planning bounds; -20 and
termination on collision or leaving the road. Progress is measured along the road so weaving and
spinning earn nothing, and stopping earns nothing while the reference speed is positive.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from gymnasium import spaces
from gymnasium.error import ResetNeeded
from highway_env.envs.common.abstract import AbstractEnv
from highway_env.envs.common.action import ContinuousAction
from highway_env.envs.common.observation import ObservationType
from highway_env.road.lane import CircularLane, LineType, StraightLane
from highway_env.road.road import Road, RoadNetwork
from highway_env.vehicle.controller import ControlledVehicle
from highway_env.vehicle.kinematics import Vehicle

from bimp.envs.checks import check_highway_config, check_policy_frequency, checked_action, checked_flag, is_real
from bimp.envs.overlay import draw_lines
from bimp.envs.road import RoadGeometry
from bimp.envs.scene import (
    ACTUATOR_ACCEL,
    ACTUATOR_STEER,
    MAX_SPEED,
    OBS_BOUND,
    OV_FIELDS,
    POLICY_FREQUENCY,
    VEHICLE_LENGTH,
    VEHICLE_WIDTH,
    Bounds,
    Scene,
    attribution_info,
    constraint_values,
    join_obs,
)
from bimp.envs.traffic import make_fast_if_known

N_OBSTACLES = 2
CRASH_PENALTY = 20.0
LANE_WIDTH, LANES = RoadGeometry.lane_width, RoadGeometry.lanes
ROAD_HALF_WIDTH = LANES * LANE_WIDTH / 2.0
# Least centre gap [m] between two vehicles that start in the same lane: a vehicle length, so the footprints do
# not overlap, plus the planning bound d_min (1 m), so the initial scene already satisfies the distance constraint
# (eq. 5) that the planners enforce; a smaller gap starts the episode in violation, or in a crash at 0.
MIN_CENTRE_GAP = VEHICLE_LENGTH + Bounds().d_min
# Largest centre gap [m] an OV may start at: 25 s away at the top speed, beyond any episode (15 s) and horizon
# (2 s), and small enough that every position stays inside the observation space (|x|, |y| <= OBS_BOUND): an OV
# can travel at most MAX_SPEED * 15 s = 600 m past it in an episode.
MAX_GAP = 1000.0

REFERENCE_COLOUR = (255, 140, 0)  # orange: no road marking or vehicle of highway-env's is drawn in it

# Keys highway-env's AbstractEnv reads; accepted as overrides (checked: bimp.envs.checks), mostly for rendering.
_HIGHWAY_KEYS = frozenset(AbstractEnv.default_config()) | {"observation", "action"}


# --- scenario parameters ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Param:
    """One scenario parameter: its default (a number, or a ``(lo, hi)`` range drawn uniformly at each reset) and
    the interval ``[low, high]`` (ends excluded where ``*_open``) that every value must lie in; ``integer``
    parameters take integers and are drawn uniformly among the integers of the range."""

    default: float | tuple[float, float]
    doc: str
    low: float = -np.inf
    high: float = np.inf
    low_open: bool = False
    high_open: bool = False
    integer: bool = False

    @property
    def rule(self) -> str:
        lo_op, hi_op = (">" if self.low_open else ">="), ("<" if self.high_open else "<=")
        kind = "an integer " if self.integer else ""
        if np.isfinite(self.low) and np.isfinite(self.high):
            return f"{kind}in {'(' if self.low_open else '['}{_fmt(self.low)}, {_fmt(self.high)}" \
                   f"{')' if self.high_open else ']'}"
        if np.isfinite(self.low):
            return f"{kind}{lo_op} {_fmt(self.low)}"
        if np.isfinite(self.high):
            return f"{kind}{hi_op} {_fmt(self.high)}"
        return kind.strip() or "a finite number"

    def admits(self, v: float) -> bool:
        above = v > self.low if self.low_open else v >= self.low
        below = v < self.high if self.high_open else v <= self.high
        return bool(above and below and (not self.integer or float(v).is_integer()))


@dataclass(frozen=True)
class Order:
    """``later`` comes after ``earlier`` by at least ``by`` (more than ``by`` where ``strict``) for *every* pair of
    draws, i.e. ``min(later) - max(earlier)``; ``later_in_steps``: ``later`` counts policy steps and is compared in
    seconds (``x dt``)."""

    earlier: str
    later: str
    doc: str
    by: float = 0.0
    strict: bool = False
    later_in_steps: bool = False

    @property
    def rule(self) -> str:
        later = f"{self.later} x dt" if self.later_in_steps else self.later
        return f"{later} {'>' if self.strict else '>='} {self.earlier}" + (f" + {_fmt(self.by)}" if self.by else "")

    def check(self, config: dict) -> None:
        scale = 1.0 / config["policy_frequency"] if self.later_in_steps else 1.0
        later, earlier = config[self.later], config[self.earlier]
        room = np.min(later) * scale - np.max(earlier)
        if room > self.by if self.strict else room >= self.by - 1e-9:
            return
        in_s = f" (x dt = {_fmt(np.min(later) * scale)} s at its least)" if self.later_in_steps else ""
        raise ValueError(f"config must have {self.rule} for every draw of the ranges ({self.doc}), got "
                         f"{self.later}={_fmt(later)}{in_s} and {self.earlier}={_fmt(earlier)}")


def _fmt(value: Any) -> str:
    if isinstance(value, tuple):
        return "(" + ", ".join(_fmt(v) for v in value) + ")"
    if is_real(value):
        return f"{float(value):g}" if float(value).is_integer() or not np.isfinite(value) else repr(float(value))
    return repr(value)


def _checked_param(key: str, value: Any, param: Param) -> float | int | tuple:
    """``value`` normalized to a float (int for integer parameters) or a ``(lo, hi)`` tuple of them; raises
    ValueError naming ``key`` and the value when it is not a number / a 2-sequence of finite numbers in order
    inside the parameter's interval."""
    if isinstance(value, np.ndarray) and value.ndim == 0:
        value = value.item()
    if is_real(value):
        values = (value,)
    elif isinstance(value, (list, tuple, np.ndarray)) and len(value) == 2 and all(is_real(v) for v in value):
        values = tuple(value)
    else:
        raise ValueError(f"{key} must be a number or a (lo, hi) range of two numbers, got {value!r}")
    shown = _fmt(values if len(values) == 2 else values[0])
    if not all(np.isfinite(v) for v in values):
        raise ValueError(f"{key} must be finite, got {shown}")
    if len(values) == 2 and values[0] > values[1]:
        raise ValueError(f"{key} range (lo, hi) must have lo <= hi, got {shown}")
    for v in values:
        if not param.admits(v):
            raise ValueError(f"{key} must be {param.rule} ({param.doc}), got {shown}")
    cast = int if param.integer else float
    out = tuple(cast(v) for v in values)
    return out if len(out) == 2 else out[0]


def _check_frequencies(config: dict, where: str) -> None:
    for key in ("simulation_frequency", "policy_frequency"):
        v = config[key]
        if not (is_real(v) and float(v).is_integer() and v > 0):
            raise ValueError(f"{key} must be a positive integer [Hz], got {v!r}")
    check_policy_frequency(config["policy_frequency"], where)
    if config["simulation_frequency"] % config["policy_frequency"]:
        raise ValueError(f"simulation_frequency must be an integer multiple of policy_frequency, got "
                         f"{config['simulation_frequency']!r} and {config['policy_frequency']!r}")


# --- vehicles ------------------------------------------------------------------------------------------------------
class _FootprintContact:
    """highway-env's collision handling switched off: the env decides contacts from the footprint gap itself.

    highway-env's ``Road.step`` calls ``handle_collisions`` for every pair; when the pair *will* intersect within
    the step at constant velocity it stores an ``impact`` translation (the separating vector, half to each) that
    the next ``Vehicle.step`` adds to the position, and it sets ``crashed``; a crashed vehicle then has its input
    overridden (steering 0, braking to a stop). All three would change the recorded motion. Here vehicles are not
    collidable, ``handle_collisions`` does nothing, and ``crashed`` (which the env sets, so highway-env draws the
    contact) never changes the dynamics.
    """

    def _no_collision_handling(self) -> None:
        self.collidable = False
        self.impact = None

    def handle_collisions(self, other, dt: float = 0.0) -> None:
        return None

    @classmethod
    def create_from(cls, vehicle) -> Vehicle:
        """A plain snapshot, for highway-env's trajectory history (``show_trajectories``); highway-env's own
        ``ControlledVehicle.create_from`` passes arguments ``ObstacleVehicle`` does not take."""
        snapshot = Vehicle(vehicle.road, vehicle.position, vehicle.heading, vehicle.speed)
        snapshot.crashed = vehicle.crashed
        if getattr(vehicle, "color", None):
            snapshot.color = vehicle.color
        return snapshot

    def clip_actions(self) -> None:
        crashed, self.crashed = self.crashed, False
        try:
            super().clip_actions()
        finally:
            self.crashed = crashed


class EgoVehicle(_FootprintContact, Vehicle):
    """highway-env's kinematic bicycle with the speed clamped at >= 0 (highway-env lets braking reverse)."""

    MIN_SPEED = 0.0

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._no_collision_handling()

    def step(self, dt: float) -> None:
        super().step(dt)
        self.speed = max(self.speed, 0.0)


class ObstacleVehicle(_FootprintContact, ControlledVehicle):
    """An OV that keeps its lane centre (highway-env's lateral controller) and follows a scripted
    acceleration: zero, or ``-decel`` from ``brake_onset`` seconds until it stands still (``decel`` is a
    magnitude, m/s^2)."""

    def __init__(self, road, position, heading, speed, lane_index, brake_onset=np.inf, decel=0.0):
        super().__init__(road, position, heading, speed, target_lane_index=lane_index, target_speed=speed)
        self.brake_onset, self.decel, self.clock, self.acceleration = brake_onset, decel, 0.0, 0.0
        self._no_collision_handling()

    def act(self, action=None) -> None:
        self.follow_road()
        braking = self.clock >= self.brake_onset and self.speed > 0.0
        Vehicle.act(self, {"steering": self.steering_control(self.target_lane_index),
                           "acceleration": -self.decel if braking else 0.0})

    def step(self, dt: float) -> None:
        v0 = self.speed
        super().step(dt)
        self.speed = max(self.speed, 0.0)
        self.clock += dt
        self.acceleration = (self.speed - v0) / dt


def _build_network(road: RoadGeometry, speed_limit: float) -> RoadNetwork:
    """highway-env lanes tracing :class:`RoadGeometry` (straight a->b, arc b->c, straight c->d)."""
    net = RoadNetwork()
    sigma = 1.0 if road.arc_angle >= 0 else -1.0
    s1, s2 = road.straight_in, road.straight_in + road.arc_length
    for i in range(road.lanes):
        c = float(road.lane_offset(i))
        lines = [LineType.CONTINUOUS_LINE if i == 0 else LineType.NONE,
                 LineType.CONTINUOUS_LINE if i == road.lanes - 1 else LineType.STRIPED]
        kw = dict(width=road.lane_width, line_types=lines, speed_limit=speed_limit)
        net.add_lane("a", "b", StraightLane(road.position(0.0, c), road.position(s1, c), **kw))
        if road.arc_length > 0:
            phase = -sigma * np.pi / 2
            # CONTINUOUS_LINE is drawn as one straight stroke: curves need the dashed-without-gaps kind.
            arc_lines = [LineType.CONTINUOUS if t == LineType.CONTINUOUS_LINE else t for t in lines]
            arc = CircularLane(road._centre, road.radius - sigma * c, phase, phase + road.arc_angle,
                               clockwise=sigma > 0, **{**kw, "line_types": arc_lines})
            net.add_lane("b", "c", arc)
        else:
            net.add_lane("b", "c", StraightLane(road.position(s1, c), road.position(s2 + 1e-3, c), **kw))
        net.add_lane("c", "d", StraightLane(road.position(s2, c), road.position(road.length, c), **kw))
    return net


class BimpObservation(ObservationType):
    """The flat observation described in the module docstring."""

    def space(self) -> spaces.Box:
        # Finite but generous: the roads are < 1 km long; SB3 and check_env dislike infinite boxes.
        return spaces.Box(-OBS_BOUND, OBS_BOUND, shape=(self.env.scene.obs_dim,), dtype=np.float32)

    def observe(self) -> np.ndarray:
        env = self.env
        ovs = np.zeros((env.scene.n_obstacles, len(OV_FIELDS)))  # an absent OV is a row of zeros: present = 0
        rows = env._ov_rows()[:len(ovs)]
        ovs[:len(rows)] = rows
        return join_obs(env._ev_state(), env.last_input, ovs, env.reference()).astype(np.float32)


@dataclass(frozen=True)
class GapAcceptance:
    """The overtaking scenario's behaviour layer: MOBIL-like gap acceptance, in time gaps at the EV's speed [s].

    Pass: the OV ahead in the EV's lane is slower than the cruise speed and within ``consider_s``; the other lane
    is free ahead for ``headway_s`` plus what the EV closes there on its OV during a pass (``pass_s``), and behind
    for ``headway_s`` at the closing speed; and the EV, at its closing speed, is more than ``lane_change_s`` from
    the OV it passes (else it brakes behind it first). Return: the passed OV is ``return_s`` behind and the lane
    ahead is free. No safe lane: keep the lane and follow the OV ahead at its speed. Part of an evaluation arm's
    config: a changed rule is a changed scenario."""

    consider_s: float = 4.0  # a slower OV closer than this is worth passing
    headway_s: float = 1.5  # the gap every lane change must leave, at the follower's speed
    pass_s: float = 6.0  # how long a pass takes, over which the EV closes on the OV ahead in the other lane
    return_s: float = 0.5  # how far the passed OV must be behind before the EV returns
    # A lane change takes about 2 s (the planners' lane-change path crosses a 4 m lane at 2 m/s); begun closer to
    # the OV than that, the swerve that clears it overshoots the far lane. On development episodes drawn in the
    # corner of the ranges (EV 26-27 m/s, OV1 25-27 m ahead at 15-16 m/s) EnKTS left the road on 10 of 200
    # without this rule and on none with it (results/tuning/lane_change/).
    lane_change_s: float = 2.0


class BimpEnv(AbstractEnv):
    """Common machinery of the two scenarios; subclasses define ``PARAMS`` (and ``ORDERS``), ``_scene_road`` and
    ``_populate``. The accepted values of every parameter are appended to each subclass's docstring from the
    very table the checks read.

    Stepping a terminated episode (after a collision or leaving the road) without ``reset`` raises
    ``gymnasium.error.ResetNeeded``, the error Gymnasium's ``OrderEnforcing`` raises for a step before the first
    reset. Raised rather than warned: past the termination the simulation has no meaning (the footprints
    overlap, nothing models the crash), and a warning, shown once, would leave every later number in a trace or
    a sum of rewards silently wrong. The check is in the env itself, not a wrapper: ``gym.make`` adds
    ``OrderEnforcing`` and ``PassiveEnvChecker``, neither of which looks at termination, and ``env.unwrapped``
    has no wrapper at all. A truncated episode (the registration's ``TimeLimit``) is the wrapper's business and
    may be stepped on, as Gymnasium allows.
    """

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": 10}
    _ended = False
    PARAMS: dict[str, Param] = {}
    OPTIONS: dict[str, tuple[str, ...]] = {}  # non-numeric scenario keys: the first choice is the default
    OVERTAKE_METRIC = False  # info["ahead_of_ov1"]: whether the EV is ahead of OV1 (the overtaking scenario)
    BEHAVIOUR: GapAcceptance | None = None  # the decision module that sets the reference, where there is one
    ORDERS: tuple[Order, ...] = ()

    def __init__(self, config: dict | None = None, render_mode: str | None = None, fast_traffic: bool = True):
        # Before highway-env's __init__, whose reset builds the first road.
        self.fast_traffic = checked_flag("fast_traffic", fast_traffic)
        super().__init__(config, render_mode)

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if cls.PARAMS and cls.__doc__:
            lines = [f"    - ``{k}`` = {_fmt(p.default)}: {p.doc}; {p.rule}" for k, p in cls.PARAMS.items()]
            lines += [f"    - {o.rule} for every draw of the ranges: {o.doc}" for o in cls.ORDERS]
            cls.__doc__ = cls.__doc__.rstrip() + "\n\n    Parameters (default; meaning; accepted values):\n\n" \
                + "\n".join(lines) + "\n"

    @classmethod
    def default_config(cls) -> dict:
        config = super().default_config()
        config.update(
            simulation_frequency=POLICY_FREQUENCY, policy_frequency=POLICY_FREQUENCY, screen_width=800,
            screen_height=240, centering_position=[0.35, 0.5], scaling=4.0,
            **{k: p.default for k, p in cls.PARAMS.items()},
            **{k: choices[0] for k, choices in cls.OPTIONS.items()},
        )
        return config

    # --- configuration ---------------------------------------------------------------------------------------
    def _checked_config(self, base: dict, overrides: dict | None) -> dict:
        """``base`` updated with ``overrides``, every scenario parameter validated and normalized, the orders
        checked; raises ValueError (naming the key and the value) before anything is changed or simulated."""
        if overrides is not None and not isinstance(overrides, Mapping):
            raise ValueError(f"config must be a mapping of config keys to values (a dict), got "
                             f"{type(overrides).__name__} {overrides!r}")
        overrides = dict(overrides or {})
        unknown = sorted(set(overrides) - set(self.PARAMS) - set(self.OPTIONS) - _HIGHWAY_KEYS)
        if unknown:
            raise ValueError(f"unknown config key(s) {unknown} for {type(self).__name__}; "
                             f"scenario keys are {sorted([*self.PARAMS, *self.OPTIONS])}")
        if "action" in overrides:  # define_spaces drives the EV by its own action: highway-env's would be ignored
            raise ValueError(f"config action={overrides['action']!r} cannot be honoured: {type(self).__name__} drives "
                             "the EV by its own continuous [acceleration, steering] action in [-1, 1] (leave it out)")
        check_highway_config(type(self).__name__, type(self), overrides, refuse_unknown=False)
        config = {**base, **overrides}
        for key, param in self.PARAMS.items():
            config[key] = _checked_param(key, config[key], param)
        for key, choices in self.OPTIONS.items():
            if config[key] not in choices:
                raise ValueError(f"{key} must be one of {list(choices)}, got {config[key]!r}")
        _check_frequencies(config, type(self).__name__)
        for order in self.ORDERS:
            order.check(config)
        return config

    def configure(self, config: dict | None) -> None:
        """Permanent configuration (``gym.make(id, config=...)``, or highway-env's ``env.unwrapped.configure``):
        the base that every ``reset`` starts from."""
        checked = self._checked_config(self.config, config)
        super().configure({k: checked[k] for k in (config or {})})
        self._base_config = copy.deepcopy(self.config)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Gymnasium's reset; ``options={"config": {...}}`` overrides the configuration for this episode only
        (highway-env's own reset would ``configure`` it permanently): every reset starts from the config given
        at ``gym.make``."""
        options = dict(options or {})
        overrides = options.pop("config", None)
        config = self._checked_config(copy.deepcopy(self._base_config), overrides)
        self.config.clear()  # in place: highway-env's viewer keeps a reference to this dict
        self.config.update(config)
        return super().reset(seed=seed, options=options or None)

    def update_metadata(self, video_real_time_ratio: float = 1) -> None:
        """``render_fps`` in real time: one frame per policy step (what gymnasium's ``RecordVideo`` captures),
        or per simulation step once highway-env's own ``set_record_video_wrapper`` captures the intermediate
        frames. highway-env's default doubles the rate (``video_real_time_ratio=2``) and writes it into the
        class-level dict shared by every instance; here each instance gets its own dict."""
        frames = self.config["simulation_frequency" if self._record_video_wrapper else "policy_frequency"]
        self.metadata = {**type(self).metadata, "render_fps": video_real_time_ratio * frames}

    def _draw(self, key: str) -> float:
        """This episode's value of ``key``, recorded in ``self.drawn_params`` (a list where a key is drawn more
        than once, e.g. ``ov_speed`` once per OV)."""
        value = self.config[key]
        if np.isscalar(value):
            drawn = value
        elif self.PARAMS[key].integer:
            drawn = int(self.np_random.integers(value[0], value[1] + 1))
        else:
            drawn = float(self.np_random.uniform(*value))
        if key in self.drawn_params:
            previous = self.drawn_params[key]
            self.drawn_params[key] = [*previous, drawn] if isinstance(previous, list) else [previous, drawn]
        else:
            self.drawn_params[key] = drawn
        return drawn

    # --- spaces ------------------------------------------------------------------------------------
    def define_spaces(self) -> None:
        if getattr(self, "scene", None) is None:
            self.scene = self._make_scene(RoadGeometry())
        self.observation_type = BimpObservation(self)
        self.action_type = ContinuousAction(self, acceleration_range=ACTUATOR_ACCEL,
                                            steering_range=ACTUATOR_STEER, clip=True)
        self.observation_space = self.observation_type.space()
        self.action_space = self.action_type.space()

    def _make_scene(self, road: RoadGeometry) -> Scene:
        return Scene(road=road.route(), geometry=road, bounds=Bounds(), dt=1.0 / self.config["policy_frequency"],
                     vehicle_length=VEHICLE_LENGTH, vehicle_width=VEHICLE_WIDTH,
                     actuator_accel=ACTUATOR_ACCEL, actuator_steer=ACTUATOR_STEER, n_obstacles=N_OBSTACLES)

    # --- episode -----------------------------------------------------------------------------------
    def _reset(self) -> None:
        self.drawn_params: dict[str, Any] = {}
        self.scene = self._make_scene(self._scene_road())
        self.road = Road(network=_build_network(self.scene.geometry, speed_limit=40.0),
                         np_random=self.np_random, record_history=self.config["show_trajectories"])
        if self.fast_traffic:  # bimp.envs.traffic: the same episodes
            make_fast_if_known(self.road)
        self.obstacles: list[ObstacleVehicle] = []
        ego_speed, lane = self._populate()
        road = self.scene.geometry
        pos = road.position(0.0, road.lane_offset(lane))
        ego = EgoVehicle(self.road, pos, float(road.heading_at(0.0)), ego_speed)
        ego.color = (50, 200, 0)  # highway-env draws crashed vehicles red; keep the EV distinct
        self.road.vehicles.insert(0, ego)
        self.road.vehicles.extend(self.obstacles)
        self.vehicle = ego
        self.ego_lane, self.cruise_speed = lane, ego_speed
        self.last_input = np.zeros(2)
        self.prev_input = np.zeros(2)
        self._safety_key = None
        self._ended = False  # a step terminated the episode: the next step raises until a reset

    def _add_obstacle(self, lane: int, s: float, speed: float, **braking) -> None:
        road = self.scene.geometry
        index = ("a", "b", lane) if s < road.straight_in else ("b", "c", lane)
        ov = ObstacleVehicle(self.road, road.position(s, road.lane_offset(lane)), float(road.heading_at(s)),
                             speed, index, **braking)
        self.obstacles.append(ov)

    def reference(self) -> np.ndarray:
        """``[v_ref m/s, dv_ref/dt m/s^2, lane offset m]`` at the current time (see subclasses)."""
        return np.array([self.cruise_speed, 0.0, self.scene.geometry.lane_offset(self.ego_lane)])

    def render(self):
        """highway-env's frame; in ``rgb_array`` mode (videos) with the reference lane drawn under the vehicles,
        ahead of the EV over the paper's 2 s horizon at the reference speed: what the behaviour layer asks for; then
        the lines a caller set in ``self.overlay`` (an agent's plan: :mod:`bimp.envs.overlay`)."""
        frame = super().render()
        if self.render_mode != "rgb_array" or self.viewer is None:
            return frame
        road = self.scene.road
        v_ref, _, lane = self.reference()
        s_e, _ = road.frenet(self.vehicle.position)
        s = s_e + np.linspace(0.0, 2.0 * max(v_ref, 5.0), 24)
        drawn = draw_lines(self, [(road.position(s, lane), REFERENCE_COLOUR, 3)])
        return frame if drawn is None else drawn

    def step(self, action):
        """highway-env's step with the action checked (real numbers, shape (2,), finite; clipped to [-1, 1]). After a
        step that terminated the episode (collision, off the road) it raises ``gymnasium.error.ResetNeeded`` until the
        next ``reset``; see the class docstring."""
        if self._ended:
            raise ResetNeeded("step() after the episode terminated (collision or off the road): call reset() first")
        action = checked_action(action)
        self.prev_input = self.last_input
        self.last_input = self.scene.to_physical(action)
        obs, reward, terminated, truncated, info = super().step(np.clip(action, -1.0, 1.0))
        self._ended = bool(terminated)
        return obs, reward, terminated, truncated, info

    def _simulate(self, action=None) -> None:
        """highway-env's ``_simulate`` (the action is applied at the first of the policy step's simulation steps),
        plus the contact check after every simulation step: the first state whose footprints overlap ends the
        step there (``time`` then says when), so the contact is what the observation and ``info`` show."""
        frames = int(self.config["simulation_frequency"] // self.config["policy_frequency"])
        dt = 1.0 / self.config["simulation_frequency"]
        for frame in range(frames):
            if frame == 0 and action is not None and not self.config["manual_control"]:
                self.action_type.act(action)
            self.road.act()
            self.road.step(dt)
            self.steps += 1
            if self._mark_contacts():
                self.time -= (frames - 1 - frame) * dt
                break
            if frame < frames - 1:
                self._automatic_rendering()
        self.enable_auto_render = False

    def _ov_rows(self) -> np.ndarray:
        """Every OV as an observation row ``(K, 6)`` (:data:`bimp.envs.scene.OV_FIELDS`)."""
        rows = [[1.0, *ov.position, ov.heading, ov.speed, ov.acceleration] for ov in self.obstacles]
        return np.array(rows).reshape(-1, len(OV_FIELDS))

    def _ev_state(self) -> np.ndarray:
        ev = self.vehicle
        return np.array([*ev.position, ev.heading, ev.speed])

    def _mark_contacts(self) -> bool:
        """Footprint contact EV-OV in the current simulated state (gap <= 0); marks the EV and the OVs it touches
        ``crashed`` (highway-env draws crashed OVs red; it does not change their motion here)."""
        hit = self.scene.ov_gaps(self._ev_state(), self._ov_rows()) <= 0.0
        for ov, touched in zip(self.obstacles, hit):
            ov.crashed |= bool(touched)
        self.vehicle.crashed |= bool(hit.any())
        return bool(hit.any())

    def _safety(self) -> dict:
        # Reward and info both need these per step: compute them once per simulated step.
        key = self.steps
        if getattr(self, "_safety_key", None) != key:
            self._safety_key, self._safety_value = key, self._compute_safety()
        return self._safety_value

    def _compute_safety(self) -> dict:
        ev, scene = self.vehicle, self.scene
        state, ovs = self._ev_state(), self._ov_rows()
        gaps = scene.ov_gaps(state, ovs)
        edge = float(scene.edge_distance(state))
        s_e, l_e = scene.road.frenet(ev.position)
        s_o, l_o = scene.road.frenet(ovs[:, 1:3])
        ahead_same_lane = (s_o > s_e) & (np.abs(l_o - l_e) < scene.vehicle_width + 0.5)
        closing = ev.speed - ovs[:, 4]
        ttc = np.where(ahead_same_lane & (closing > 1e-6), np.maximum(gaps, 0.0) / np.maximum(closing, 1e-6), np.inf)
        ref = self.reference()
        b, u = scene.bounds, self.last_input
        constraints = constraint_values(b, u, self.prev_input, gaps, edge)
        heading_err = ev.heading - float(scene.road.heading_at(s_e))
        # The closed-loop score's per-step facts: the OV touched, if any, and the limit. The road has no speed limit
        # of its own (its lanes carry highway-env's 40 m/s, the top speed): the limit is the free-road cruise speed,
        # the EV's initial speed that the reference holds on a free road. The lateral speed is across the road at
        # the EV's arc length (the bicycle's slip angle, at most 0.025 rad within the planning bounds, left out).
        attribution = attribution_info(state, ovs, gaps, ev_lateral_speed=float(ev.speed * np.sin(heading_err)),
                                       speed_limit=self.cruise_speed)
        return {
            "collision": bool(np.any(gaps <= 0.0)), "offroad": edge < 0.0, "ov_distance": gaps.tolist(),
            "edge_distance": edge, "ttc": float(ttc.min()), "reference": ref.tolist(),
            "lateral_error": float(l_e - ref[2]), "speed_error": float(ev.speed - ref[0]),
            "longitudinal_speed": float(ev.speed * np.cos(heading_err)), "s": float(s_e),
            "input": u.tolist(), "constraints": constraints,
            "ahead_of_ov1": bool(s_e > s_o[0]) if self.OVERTAKE_METRIC else None, **attribution,
        }

    def _info(self, obs, action=None) -> dict:
        return self._safety()

    def _rewards(self, action) -> dict[str, float]:
        info = self._safety()
        v_ref = info["reference"][0]
        ref_speed = max(v_ref, 1.0)
        c = info["constraints"]
        excess = max(c["accel_min"], c["accel_max"], 0.0) / 3.0 + max(c["steer"], 0.0) / 0.05 \
            + max(c["accel_rate"], 0.0) + max(c["steer_rate"], 0.0) / 0.005
        return {
            "speed": float(np.exp(-((info["longitudinal_speed"] - v_ref) / (0.5 * ref_speed)) ** 2)),
            "lane": float(np.exp(-(info["lateral_error"] / 1.5) ** 2)),
            "inputs": float(min(excess, 5.0)),
            "crash": float(info["collision"] or info["offroad"]),
        }

    def _reward(self, action) -> float:
        r = self._rewards(action)
        return 0.6 * r["speed"] + 0.4 * r["lane"] - 0.1 * r["inputs"] - CRASH_PENALTY * r["crash"]

    def _is_terminated(self) -> bool:
        info = self._safety()
        return info["collision"] or info["offroad"]

    def _is_truncated(self) -> bool:
        return False  # the time limit lives in the registration

    # --- subclass hooks ----------------------------------------------------------------------------
    def _scene_road(self) -> RoadGeometry:
        raise NotImplementedError

    def _populate(self) -> tuple[float, int]:
        """Place the OVs (``self._add_obstacle``) and return the EV's initial speed and lane."""
        raise NotImplementedError


class OvertakingEnv(BimpEnv):
    """Paper V-A: curved two-lane highway; the EV (right lane, ~25 m/s) closes on two slower OVs that hold
    speed and lane: OV1 ahead in the EV's lane, OV2 further ahead in the left lane.

    The reference comes from the paper's "higher-level decision-making module" (section II), a behaviour layer
    in the env (``reference: behaviour``, the default): gap acceptance in the spirit of MOBIL sets the reference
    lane and speed at every step from the traffic. It passes a slower OV ahead when the other lane is free over a
    safe window (a headway ahead plus what the EV closes during a pass, a headway behind), returns to the right
    lane once the passed OV is behind by a safe gap, and when no lane is safe keeps its lane and follows the
    slower OV at its speed; it only ever names a lane of the road. ``reference: keep-lane`` is the discovery
    variant: the right lane at the EV's initial speed, so passing needs the constraints to push the plan off the
    reference. ``info["ahead_of_ov1"]``: the EV is ahead of OV1 (``overtake_rate`` of an episode is its last
    value). ``gap``s are measured between vehicle centres along the road [m]; speeds in m/s; ``arc_angle_deg``
    > 0 turns right. Episode: 15 s (150 steps)."""

    PARAMS = {
        "ev_speed": Param((23.0, 27.0), "EV initial and reference speed, m/s", 0.0, MAX_SPEED),
        "ov1_gap": Param((25.0, 35.0), "centre gap of OV1 (EV's lane) ahead of the EV, m", MIN_CENTRE_GAP, MAX_GAP),
        "ov1_speed": Param((15.0, 17.0), "OV1 speed, m/s", 0.0, MAX_SPEED),
        "ov2_gap": Param((100.0, 130.0), "centre gap of OV2 (left lane) ahead of the EV, m", MIN_CENTRE_GAP, MAX_GAP),
        "ov2_speed": Param((18.0, 20.0), "OV2 speed, m/s", 0.0, MAX_SPEED),
        "radius": Param((180.0, 220.0), "arc radius of the centreline, m, beyond the road's half width",
                        ROAD_HALF_WIDTH, low_open=True),
        "arc_angle_deg": Param((50.0, 70.0), "arc angle, degrees, > 0 turns right; at most a quarter turn, "
                               "so the straight after the arc never runs back beside the road", -90.0, 90.0),
    }
    # OV2 outpaces OV1 so that a pass exists on every instance: with OV2 no faster, the EV in the passing lane is
    # held at OV2's pace and may never get past OV1 (tests/envs/test_feasibility.py; on tuning seeds 100-199 of the
    # old ranges, 15-18 and 17-20 m/s, the 4 instances neither planner passed had OV2 at most 0.1 m/s faster).
    ORDERS = (Order("ov1_gap", "ov2_gap", "OV2 starts further ahead than OV1, clear of it even in one lane",
                    by=MIN_CENTRE_GAP),
              Order("ov1_speed", "ov2_speed", "OV2, ahead in the passing lane, outpaces OV1", by=1.0))
    OPTIONS = {"reference": ("behaviour", "keep-lane")}
    OVERTAKE_METRIC = True

    BEHAVIOUR = GapAcceptance()

    def _scene_road(self) -> RoadGeometry:
        return RoadGeometry(straight_in=100.0, radius=self._draw("radius"),
                            arc_angle=np.deg2rad(self._draw("arc_angle_deg")), straight_out=300.0)

    def _populate(self) -> tuple[float, int]:
        ev_speed = self._draw("ev_speed")
        self._add_obstacle(1, self._draw("ov1_gap"), self._draw("ov1_speed"))
        self._add_obstacle(0, self._draw("ov2_gap"), self._draw("ov2_speed"))
        self.target_lane, self.reference_speed = 1, ev_speed
        return ev_speed, 1

    def _reset(self) -> None:
        super()._reset()
        self._behave()

    def _simulate(self, action=None) -> None:
        super()._simulate(action)
        self._behave()  # the reference the next observation publishes

    def reference(self) -> np.ndarray:
        """The behaviour layer's lane and speed (``reference: behaviour``), or the EV's own lane at the cruise
        speed (``keep-lane``, the discovery variant: passing is left to the planner)."""
        if self.config["reference"] == "keep-lane":
            return super().reference()
        return np.array([self.reference_speed, 0.0, self.scene.geometry.lane_offset(self.target_lane)])

    def _traffic(self) -> tuple[float, float, list[tuple[float, float, int]]]:
        """The EV's arc length and speed, and each OV's ``(s, speed, lane)`` (lane: the nearest centre)."""
        road = self.scene.geometry
        s_e, _ = road.to_frenet(self.vehicle.position)
        rows = []
        for ov in self.obstacles:
            s_o, l_o = road.to_frenet(ov.position)
            lane = int(np.argmin(np.abs(l_o - road.lane_offset(np.arange(road.lanes)))))
            rows.append((float(s_o), float(ov.speed), lane))
        return float(s_e), float(self.vehicle.speed), rows

    def _behave(self) -> None:
        """Gap acceptance in the spirit of MOBIL: sets ``target_lane`` (always a lane of the road) and
        ``reference_speed`` from the traffic."""
        s_e, v_e, ovs = self._traffic()
        b = self.BEHAVIOUR
        length, cruise = self.scene.vehicle_length + self.scene.bounds.d_min, self.cruise_speed

        def ahead(lane):
            rows = [(s - s_e, v) for s, v, k in ovs if k == lane and s > s_e]
            return min(rows, default=(np.inf, np.inf))

        def behind(lane):
            rows = [(s_e - s, v) for s, v, k in ovs if k == lane and s <= s_e]
            return min(rows, default=(np.inf, 0.0))

        def free(lane):
            gap_a, v_a = ahead(lane)
            gap_b, v_b = behind(lane)
            closing = max(v_e - v_a, 0.0) * b.pass_s if np.isfinite(v_a) else 0.0
            return (gap_a - length >= b.headway_s * v_e + closing
                    and gap_b - length >= b.headway_s * max(v_b - v_e, 0.0) + b.return_s * v_e)

        current, other = self.target_lane, 1 - self.target_lane
        gap, v_lead = ahead(current)
        slower_ahead = v_lead < cruise - 0.5 and gap < b.consider_s * max(v_e, 1.0)
        if current == 0 and free(1):  # keep right: return once the passed OV is behind and the lane is clear
            self.target_lane = 1
        elif slower_ahead and free(other) and gap - length > b.lane_change_s * (v_e - v_lead):
            self.target_lane = other
        gap, v_lead = ahead(self.target_lane)
        # No safe lane: follow the slower OV ahead at its speed.
        follow = v_lead < cruise and gap < b.consider_s * max(v_e, 1.0)
        self.reference_speed = float(v_lead) if follow else cruise


class OvertakingKeepLaneEnv(OvertakingEnv):
    """:class:`OvertakingEnv` with ``reference: keep-lane`` as its default (``bimp/OvertakingKeepLane-v0``): the
    reference holds the right lane at the EV's initial speed, so a pass must be discovered by the planner, pushed
    off the reference by the constraints (the paper's V-A setting; the claims study's exploration test)."""

    OPTIONS = {"reference": ("keep-lane", "behaviour")}


class EmergencyBrakeEnv(BimpEnv):
    """Paper V-B: straight two-lane road; an OV ahead in each lane brakes hard (``brake_decel`` m/s^2, a
    magnitude: the OVs accelerate by ``-brake_decel``) to a full stop from ``brake_onset`` s (sudden traffic
    build-up). The reference speed holds the cruise
    value (the EV's initial speed) for ``ref_hold`` s, then falls linearly to 0 at step ``ref_zero_step``.
    The EV must stop without collision and stay on the road. Episode: 12 s (120 steps)."""

    PARAMS = {
        "ev_speed": Param((23.0, 27.0), "EV initial (cruise) speed, m/s", 0.0, MAX_SPEED),
        # From 50 m: braking at the planning bounds (a_min, rate-limited) from the first observed deceleration
        # keeps >= d_min to OV1 on every instance of the ranges (worst corner 2.1 m; with 40 m it was -7.9 m:
        # tests/envs/test_feasibility.py).
        "ov1_gap": Param((50.0, 60.0), "centre gap of OV1 (EV's lane) ahead of the EV, m", MIN_CENTRE_GAP, MAX_GAP),
        "ov2_gap": Param((35.0, 55.0), "centre gap of OV2 (left lane) ahead of the EV, m", MIN_CENTRE_GAP, MAX_GAP),
        "ov_speed": Param((20.0, 24.0), "OV speed before braking (drawn per OV), m/s", 0.0, MAX_SPEED),
        "brake_onset": Param((0.8, 1.2), "time at which the OVs start braking, s", 0.0),
        "brake_decel": Param((5.0, 7.0), "a deceleration magnitude, m/s^2", 0.0, low_open=True),
        "ref_hold": Param(3.0, "time the reference speed holds the cruise speed, s", 0.0),
        "ref_zero_step": Param(80, "policy step at which the reference speed reaches 0", 1, integer=True),
    }
    ORDERS = (Order("ref_hold", "ref_zero_step", "the reference falls to 0 only after it stops holding",
                    strict=True, later_in_steps=True),)

    def _scene_road(self) -> RoadGeometry:
        return RoadGeometry(straight_in=100.0, arc_angle=0.0, straight_out=400.0)

    def _populate(self) -> tuple[float, int]:
        ev_speed = self._draw("ev_speed")
        onset, decel = self._draw("brake_onset"), self._draw("brake_decel")
        self._add_obstacle(1, self._draw("ov1_gap"), self._draw("ov_speed"), brake_onset=onset, decel=decel)
        self._add_obstacle(0, self._draw("ov2_gap"), self._draw("ov_speed"), brake_onset=onset, decel=decel)
        # ORDERS guarantees ref_zero > ref_hold for every draw.
        self.ref_hold, self.ref_zero = self._draw("ref_hold"), self._draw("ref_zero_step") * self.scene.dt
        return ev_speed, 1

    def reference(self) -> np.ndarray:
        ref = super().reference()
        slope = self.cruise_speed / (self.ref_zero - self.ref_hold)
        t = self.time
        if t < self.ref_hold:
            return ref
        if t >= self.ref_zero - 1e-9:
            return np.array([0.0, 0.0, ref[2]])
        return np.array([self.cruise_speed - slope * (t - self.ref_hold), -slope, ref[2]])
