"""The paper's two scenarios (section V) as highway-env environments.

Both share :class:`BimpEnv`: a two-lane road of 4 m lanes, dt = 0.1 s (simulation and policy frequency
10 Hz), the EV driven by a continuous ``[acceleration, steering]`` action in [-1, 1] that maps linearly
onto actuator ranges wider than the planning bounds (so violations of the bounds are measurable).
**Actions outside [-1, 1] are clipped; a non-finite action raises ValueError.** Speeds never go negative.

Configuration: ``gym.make(id, config={...})``. Scenario parameters given as a 2-sequence ``(lo, hi)`` are
drawn uniformly from ``self.np_random`` at every ``reset(seed=...)``; a number fixes them. An unknown key
raises ``ValueError`` naming it. ``reset(options={"config": {...}})`` overrides them the same way.

Collision: ``info["collision"]`` is true exactly when the EV's footprint touches or overlaps an OV's, i.e. when
``min(info["ov_distance"]) <= 0``, the exact signed distance between the two 5 m x 2 m rectangles
(:meth:`envs.scene.Scene.ov_gaps`). It is measured on the simulated state itself: highway-env's collision handling
(which predicts an intersection one step ahead, pushes both vehicles apart by an "impact" translation and then
brakes crashed vehicles to a stop) is switched off for all vehicles, so no contact moves anyone, OV-OV contacts
included. The env checks the gap after every simulation step and ends the step at the first overlapping state.
The EV and the OVs it touches are marked ``crashed`` only so that highway-env draws them so.

Observation (flat ``Box``, float32, see :mod:`envs.scene`): EV ``[x, y, heading, speed]``, the previous
physical input ``[a, delta]``, per OV ``[present, x, y, heading, speed, acceleration]``, and the reference
``[v_ref, dv_ref/dt, lateral offset of the reference lane]``.

``info`` per step: ``collision``, ``offroad`` (any body corner past a road edge), ``ov_distance`` (signed
footprint gap to each OV, see above), ``edge_distance`` (least corner distance to the edge), ``ttc`` (time to
collision with the nearest closing OV in the EV's lane), ``reference``, ``lateral_error``, ``speed_error``,
``input`` (the physical input applied) and ``constraints`` (paper eq. 2-5 as values that are <= 0 when satisfied).

Reward (for RL): tracking of the reference speed measured *along the road* and of the reference lane,
in [0, 1] per step, minus small penalties for inputs and rate beyond the planning bounds; -20 and
termination on collision or leaving the road. Progress is measured along the road so weaving and
spinning earn nothing, and stopping earns nothing while the reference speed is positive.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces
from highway_env.envs.common.abstract import AbstractEnv
from highway_env.envs.common.action import ContinuousAction
from highway_env.envs.common.observation import ObservationType
from highway_env.road.lane import CircularLane, LineType, StraightLane
from highway_env.road.road import Road, RoadNetwork
from highway_env.vehicle.controller import ControlledVehicle
from highway_env.vehicle.kinematics import Vehicle

from envs.road import RoadGeometry
from envs.scene import Bounds, Scene

ACTUATOR_ACCEL = (-10.0, 10.0)
ACTUATOR_STEER = (-0.3, 0.3)
N_OBSTACLES = 2
CRASH_PENALTY = 20.0
OBS_BOUND = 1e4

# Keys highway-env's AbstractEnv reads; accepted as overrides, mostly for rendering.
_HIGHWAY_KEYS = frozenset(AbstractEnv.default_config()) | {"observation", "action"}


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
        env, ev = self.env, self.env.vehicle
        ovs = np.zeros((N_OBSTACLES, 6))
        for k, ov in enumerate(env.obstacles[:N_OBSTACLES]):
            ovs[k] = [1.0, *ov.position, ov.heading, ov.speed, ov.acceleration]
        ref = env.reference()
        return np.concatenate(
            [[*ev.position, ev.heading, ev.speed], env.last_input, ovs.ravel(), ref]
        ).astype(np.float32)


class BimpEnv(AbstractEnv):
    """Common machinery of the two scenarios; subclasses define ``PARAMS``, ``_scene_road`` and ``_populate``."""

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": 10}
    PARAMS: dict[str, Any] = {}

    @classmethod
    def default_config(cls) -> dict:
        config = super().default_config()
        config.update(
            simulation_frequency=10, policy_frequency=10, screen_width=800, screen_height=240,
            centering_position=[0.35, 0.5], scaling=4.0, **cls.PARAMS,
        )
        return config

    def configure(self, config: dict | None) -> None:
        unknown = sorted(set(config or {}) - set(self.PARAMS) - _HIGHWAY_KEYS)
        if unknown:
            raise ValueError(f"unknown config key(s) {unknown} for {type(self).__name__}; "
                             f"scenario keys are {sorted(self.PARAMS)}")
        for key, value in (config or {}).items():
            if key in self.PARAMS and not (np.isscalar(value) or len(value) == 2):
                raise ValueError(f"config {key!r} must be a number or a (lo, hi) range, got {value!r}")
        super().configure(config)
        if self.config["simulation_frequency"] % self.config["policy_frequency"]:
            raise ValueError("simulation_frequency must be an integer multiple of policy_frequency")

    def _draw(self, key: str) -> float:
        value = self.config[key]
        return float(value) if np.isscalar(value) else float(self.np_random.uniform(*value))

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
        return Scene(road=road, bounds=Bounds(), dt=1.0 / self.config["policy_frequency"],
                     vehicle_length=Vehicle.LENGTH, vehicle_width=Vehicle.WIDTH,
                     actuator_accel=ACTUATOR_ACCEL, actuator_steer=ACTUATOR_STEER, n_obstacles=N_OBSTACLES)

    # --- episode -----------------------------------------------------------------------------------
    def _reset(self) -> None:
        self.scene = self._make_scene(self._scene_road())
        self.road = Road(network=_build_network(self.scene.road, speed_limit=40.0),
                         np_random=self.np_random, record_history=self.config["show_trajectories"])
        self.obstacles: list[ObstacleVehicle] = []
        ego_speed, lane = self._populate()
        road = self.scene.road
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

    def _add_obstacle(self, lane: int, s: float, speed: float, **braking) -> None:
        road = self.scene.road
        index = ("a", "b", lane) if s < road.straight_in else ("b", "c", lane)
        ov = ObstacleVehicle(self.road, road.position(s, road.lane_offset(lane)), float(road.heading_at(s)),
                             speed, index, **braking)
        self.obstacles.append(ov)

    def reference(self) -> np.ndarray:
        """``[v_ref m/s, dv_ref/dt m/s^2, lane offset m]`` at the current time (see subclasses)."""
        return np.array([self.cruise_speed, 0.0, self.scene.road.lane_offset(self.ego_lane)])

    def step(self, action):
        action = np.asarray(action, dtype=float).reshape(-1)
        if action.shape != (2,):
            raise ValueError(f"action must have shape (2,), got {np.shape(action)}")
        if not np.all(np.isfinite(action)):
            raise ValueError(f"action must be finite, got {action}")
        self.prev_input = self.last_input
        self.last_input = self.scene.to_physical(action)
        return super().step(np.clip(action, -1.0, 1.0))

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
        return np.array([[1.0, *ov.position, ov.heading, ov.speed, ov.acceleration] for ov in self.obstacles])

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
        s_e, l_e = scene.road.to_frenet(ev.position)
        s_o, l_o = scene.road.to_frenet(ovs[:, 1:3])
        ahead_same_lane = (s_o > s_e) & (np.abs(l_o - l_e) < scene.vehicle_width + 0.5)
        closing = ev.speed - ovs[:, 4]
        ttc = np.where(ahead_same_lane & (closing > 1e-6), np.maximum(gaps, 0.0) / np.maximum(closing, 1e-6), np.inf)
        ref = self.reference()
        b, u, du = scene.bounds, self.last_input, self.last_input - self.prev_input
        constraints = {
            "accel_min": b.accel[0] - u[0], "accel_max": u[0] - b.accel[1], "steer": abs(u[1]) - b.steer,
            "accel_rate": abs(du[0]) - b.accel_rate, "steer_rate": abs(du[1]) - b.steer_rate,
            "ov_distance": (b.d_min - gaps).tolist(), "road_edge": b.edge_margin - edge,
        }
        heading_err = ev.heading - float(scene.road.heading_at(s_e))
        return {
            "collision": bool(np.any(gaps <= 0.0)), "offroad": edge < 0.0, "ov_distance": gaps.tolist(),
            "edge_distance": edge, "ttc": float(ttc.min()), "reference": ref.tolist(),
            "lateral_error": float(l_e - ref[2]), "speed_error": float(ev.speed - ref[0]),
            "longitudinal_speed": float(ev.speed * np.cos(heading_err)), "s": float(s_e),
            "input": u.tolist(), "constraints": constraints,
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
    speed and lane: OV1 ahead in the EV's lane, OV2 further ahead in the left lane. The reference is the
    right lane's centre at the EV's initial (desired) speed, so passing needs the constraints to push the
    plan off the reference. ``gap``s are measured between vehicle centres along the road [m]; speeds in m/s;
    ``arc_angle_deg`` > 0 turns right. Episode: 15 s (150 steps)."""

    PARAMS = {
        "ev_speed": (23.0, 27.0),
        "ov1_gap": (25.0, 35.0),
        "ov1_speed": (15.0, 18.0),
        "ov2_gap": (100.0, 130.0),
        "ov2_speed": (17.0, 20.0),
        "radius": (180.0, 220.0),
        "arc_angle_deg": (50.0, 70.0),
    }

    def _scene_road(self) -> RoadGeometry:
        return RoadGeometry(straight_in=100.0, radius=self._draw("radius"),
                            arc_angle=np.deg2rad(self._draw("arc_angle_deg")), straight_out=300.0)

    def _populate(self) -> tuple[float, int]:
        ev_speed = self._draw("ev_speed")
        self._add_obstacle(1, self._draw("ov1_gap"), self._draw("ov1_speed"))
        self._add_obstacle(0, self._draw("ov2_gap"), self._draw("ov2_speed"))
        return ev_speed, 1


class EmergencyBrakeEnv(BimpEnv):
    """Paper V-B: straight two-lane road; an OV ahead in each lane brakes hard (``brake_decel`` m/s^2) to
    a full stop from ``brake_onset`` s (sudden traffic build-up). The reference speed holds the cruise
    value (the EV's initial speed) for ``ref_hold`` s, then falls linearly to 0 at step ``ref_zero_step``.
    The EV must stop without collision and stay on the road. Episode: 12 s (120 steps)."""

    PARAMS = {
        "ev_speed": (23.0, 27.0),
        "ov1_gap": (40.0, 55.0),
        "ov2_gap": (35.0, 55.0),
        "ov_speed": (20.0, 24.0),
        "brake_onset": (0.8, 1.2),
        "brake_decel": (5.0, 7.0),
        "ref_hold": 3.0,
        "ref_zero_step": 80,
    }

    def _scene_road(self) -> RoadGeometry:
        return RoadGeometry(straight_in=100.0, arc_angle=0.0, straight_out=400.0)

    def _populate(self) -> tuple[float, int]:
        ev_speed = self._draw("ev_speed")
        onset, decel = self._draw("brake_onset"), self._draw("brake_decel")
        self._add_obstacle(1, self._draw("ov1_gap"), self._draw("ov_speed"), brake_onset=onset, decel=decel)
        self._add_obstacle(0, self._draw("ov2_gap"), self._draw("ov_speed"), brake_onset=onset, decel=decel)
        self.ref_hold, self.ref_zero = self._draw("ref_hold"), self._draw("ref_zero_step") * self.scene.dt
        if self.ref_zero <= self.ref_hold:
            raise ValueError("ref_zero_step must come after ref_hold")
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
