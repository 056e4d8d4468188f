"""The machinery the paper's scenarios share: their constants, observation, gap-acceptance rule and base env
:class:`BimpEnv` (what they are and how to configure them: :mod:`bimp.envs.scenarios`)."""

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
from highway_env.road.road import Road

from bimp.envs.checks import check_highway_config, checked_action, checked_flag
from bimp.envs.overlay import draw_lines
from bimp.envs.paper_params import Order, Param, _check_frequencies, _checked_param, _fmt
from bimp.envs.paper_vehicles import EgoVehicle, ObstacleVehicle, _build_network
from bimp.envs.road import RoadGeometry
from bimp.envs.scene import (
    ACTUATOR_ACCEL,
    ACTUATOR_STEER,
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


