"""Any supported highway-env env as a bimp env: :func:`wrap` (``bimp.envs.wrap``) and the ``bimp/ID`` entry points.

``wrap(gym.make(ID, config={...}))`` returns a :class:`HighwayAdapter` that every bimp policy drives:

- **actions**: the normalized Box [-1, 1]^2 ``[acceleration, steering]``, mapped by highway-env's
  ``ContinuousAction`` (clipped) onto the id's actuator ranges (:data:`PROFILES`), at ``policy_frequency`` 10 Hz
  and ``simulation_frequency`` 10 Hz (or a multiple of 10 that the config names, e.g. 20);
- **scene**: a new :class:`bimp.envs.scene.Scene` at every reset and step, published as ``env.unwrapped.scene``:
  the road ahead of the EV (:func:`bimp.envs.highway.lanes.build_route`: the EV's lane continued along its route,
  from at least 30 m behind to at least 250 m ahead, edges from the lanes beside it; built 100 m longer and kept
  while it serves, :class:`bimp.envs.highway.lanes.RouteCache`) and the id's planning bounds (:data:`PROFILES`);
- **observation**: bimp's layout (:func:`bimp.envs.scene.join_obs`) with ``n_obstacles`` OV slots (default 8): the
  nearest vehicles and road objects (merge-v0's end-of-ramp obstacle) by centre distance, absent slots zeros; an
  OV's acceleration is its speed change over the last step; the reference ``[v_ref, a_ref, l_ref]`` comes from the
  behaviour layer (:mod:`bimp.envs.highway.behaviour`): ``v_ref`` the EV's speed and ``a_ref`` highway-env's IDM
  acceleration there (clipped to the planning bounds), so the reference speed over a horizon is IDM's, and
  ``l_ref`` the lateral offset of MOBIL's target lane in the route's frame abreast of the EV (0 when it is the
  EV's own lane);
- **info**: highway-env's own keys (``speed``, ``crashed``, ``rewards`` ...) plus bimp's safety quantities:
  ``collision`` (highway-env's crash flag, or a footprint gap <= 0 to any vehicle or object), ``offroad`` (a body
  corner on no lane of the network, asked where the route's edges put a corner outside; or highway-env's
  ``on_road`` false, unless the centre is in a seam between two lanes of one road), ``ov_distance`` (footprint
  gaps to the K slots, inf where absent), ``edge_distance``, ``ttc``, ``s`` (the EV's progress along its route
  [m], cumulative across the republished scenes), ``reference``, ``lateral_error``, ``speed_error`` (speed minus
  the free-road target speed), ``longitudinal_speed``, ``input``, ``constraints`` (as the paper's envs report them),
  ``ahead_of_ov1`` (None), and for the closed-loop score (:func:`bimp.envs.scene.attribution_info`,
  ``docs/suite.md``) ``contact`` (None, or the vehicle in contact: the least footprint gap <= 0, else the nearest
  one highway-env flags crashed) and ``speed_limit`` (the EV's lane's ``speed_limit``, else the free-road target);
- **reward and termination**: highway-env's (crash, its off-road where it has one, its goals, its duration), and
  the episode also terminates on bimp's ``collision`` or ``offroad``; where highway-env would end it off the road
  with the EV's centre in a seam between two lanes (its ``on_road`` asks the EV's own lane only), bimp's
  ``offroad`` decides, and the episode goes on, and at ``info["goal"]``: exit-v0's exit lane
  reached, roundabout-v0's last road reached (highway-env rewards them but drives on, off the end of its network);
  a step after termination raises ``gymnasium.error.ResetNeeded``.

The env under the adapter is a new instance of the id's adapted class (:func:`bimp.envs.highway.fixed
.adapted_class`: highway-env's own, or the fixed subclass where highway-env fails under continuous actions) built
from the given env's configuration; the given env is left as it was. highway-env's ``observation`` config is
replaced by the adapter's. A config the adapter cannot honour raises ``ValueError`` naming the key: an action type
other than ``ContinuousAction`` (discrete actions), a one-axis or dynamical ``ContinuousAction``, a
``policy_frequency`` other than 10 Hz (the planners plan at dt = 0.1 s), a ``simulation_frequency`` that is not a
multiple of 10 Hz; highway-env's own keys that it would fail on (a count that is no int, a lane past the road, more
than :data:`bimp.envs.checks.MAX_VEHICLES` vehicles, a NaN reward weight: :func:`bimp.envs.checks
.check_highway_config`) and, on highway-env's ids, keys it does not have; and so does an id outside :data:`SUPPORTED`.

The suite's families (:mod:`bimp.envs.suite`, issue 27) are highway-env envs of bimp's own and run through this very
adapter: each under its ``ID`` (``"stalled-vehicle-v0"``) in :data:`PROFILES` (its numbers read from its class) and
in :data:`ENV_CLASSES`, with an entry point ``make_<ID>`` made from the table. :data:`SUPPORTED` stays highway-env's
own ids.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.error import ResetNeeded

from bimp.envs.checks import check_highway_config, check_policy_frequency, checked_action, checked_flag, is_int
from bimp.envs.highway.behaviour import Behaviour, BehaviourRule, curve_acceleration
from bimp.envs.highway.fixed import HIGHWAY_CLASSES, adapted_class
from bimp.envs.highway.lanes import RouteCache, check_steering_reach, coordinates, off_lanes, on_lanes_of, route_from
from bimp.envs.highway.prediction import lane_paths
from bimp.envs.highway.profiles import PROFILES, SUPPORTED
from bimp.envs.overlay import draw_lines
from bimp.envs.road import Projection, Route, body_corners, corner_edge_margin
from bimp.envs.scene import (
    ACTUATOR_ACCEL,
    OBS_BOUND,
    OV_FIELDS,
    POLICY_FREQUENCY,
    VEHICLE_LENGTH,
    VEHICLE_WIDTH,
    Scene,
    attribution_info,
    constraint_values,
    join_obs,
)
from bimp.envs.suite import FAMILIES
from bimp.envs.traffic import make_fast_if_known

N_OBSTACLES = 8
_VIEW_KEYS = frozenset({"screen_width", "screen_height", "centering_position", "scaling", "show_trajectories",
                        "render_agent", "offscreen_rendering", "manual_control", "real_time_rendering"})
JUNCTION_MARGIN = 1.0  # m: see lanes.off_lanes
# m: highway-env's lanes of one road may leave a seam between them, which its on_road (the EV's own lane only) counts
# as off the road: racetrack-v0's road f-g has 5 m lanes 5.08 m apart, painted as one road. See lanes.off_lanes.
SEAM_MARGIN = 0.25
PROGRESS_WINDOW = 80.0  # m of the road before a step about the EV (a quarter behind) that its progress is read on


# The env class behind every key of PROFILES: highway-env's (fixed.HIGHWAY_CLASSES) and the families'.
ENV_CLASSES: dict[str, type] = {**HIGHWAY_CLASSES, **{cls.ID: cls for cls in FAMILIES.values()}}


# The ids whose profile's duration replaces highway-env's (profiles.py says why).
LONGER = ("racetrack-v0", "roundabout-v0", "intersection-v0")


def adapter_config(highway_id: str, config: Mapping | None, base: Mapping | None = None) -> dict:
    """``config`` (highway-env keys, as for ``gym.make(highway_id, config=...)``) with the adapter's action and
    frequencies, checked: ``ValueError`` naming a key whose value the adapter cannot honour, or one highway-env would
    fail on (:func:`bimp.envs.checks.check_highway_config`). ``base``: the config ``config`` updates (the env's, at a
    reset), for the checks across keys."""
    if highway_id not in PROFILES:
        families = [i for i in PROFILES if i not in SUPPORTED]
        raise ValueError(f"the adapter has no profile for {highway_id!r}: it takes highway-env's ids "
                         f"{list(SUPPORTED)} (bimp.envs.wrap(gym.make(ID))) and the suite's families {families} "
                         f"(gym.make('bimp/ID'))")
    if config is not None and not isinstance(config, Mapping):
        raise ValueError(f"config must be a mapping of highway-env config keys (a dict), got {config!r}")
    config = dict(config or {})
    profile = PROFILES[highway_id]
    action = dict(config.get("action") or {"type": "ContinuousAction"})
    if action.get("type") != "ContinuousAction":
        raise ValueError(f"{highway_id}: config action type {action.get('type')!r} cannot be honoured: bimp drives "
                         "continuous [acceleration, steering] actions (leave 'action' out, or 'ContinuousAction')")
    for key, wanted in (("longitudinal", True), ("lateral", True), ("dynamical", False)):
        if action.get(key, wanted) != wanted:
            raise ValueError(f"{highway_id}: config action {key}={action[key]!r} cannot be honoured: bimp drives "
                             f"both acceleration and steering of the kinematic vehicle ({key} must be {wanted})")
    accel = tuple(action.get("acceleration_range", ACTUATOR_ACCEL))
    steer = tuple(action.get("steering_range", profile.actuator_steer))
    b = profile.bounds
    if not (accel[0] <= b.accel[0] and accel[1] >= b.accel[1] and steer[0] <= -b.steer and steer[1] >= b.steer):
        raise ValueError(f"{highway_id}: config action ranges {accel}, {steer} must contain the planning bounds "
                         f"accel {b.accel}, steer ±{b.steer}")
    check_policy_frequency(config.get("policy_frequency", POLICY_FREQUENCY), highway_id)
    simulation = config.get("simulation_frequency", POLICY_FREQUENCY)
    if not is_int(simulation) or simulation <= 0 or simulation % POLICY_FREQUENCY:
        raise ValueError(f"{highway_id}: config simulation_frequency={simulation!r} must be a positive multiple "
                         f"of the policy frequency {POLICY_FREQUENCY} Hz")
    # highway-env's own ids take only their own keys; a family refuses unknown ones itself, naming its own.
    check_highway_config(highway_id, ENV_CLASSES[highway_id], config, base, refuse_unknown=highway_id in SUPPORTED)
    config.pop("observation", None)
    config.update(action={"type": "ContinuousAction", "acceleration_range": accel, "steering_range": steer,
                          "longitudinal": True, "lateral": True, "dynamical": False, "clip": True},
                  policy_frequency=POLICY_FREQUENCY, simulation_frequency=int(simulation))
    if highway_id in LONGER and "duration" not in config:
        config["duration"] = profile.duration
    return config


def make(highway_id: str, config: Mapping | None = None, render_mode: str | None = None,
         n_obstacles: int = N_OBSTACLES, fast_traffic: bool = True, **kwargs) -> "HighwayAdapter":
    """The adapted env of ``highway_id`` (what ``gym.make("bimp/" + highway_id, config=..., n_obstacles=...)``
    builds, without gymnasium's wrappers). ``fast_traffic``: the road on bimp's fast traffic core
    (:mod:`bimp.envs.traffic`, the same episodes), else highway-env's own. ``kwargs``: the env class's own (a suite
    family's ``difficulty``, which its ``-easy``/``-hard`` ids pass)."""
    config = adapter_config(highway_id, config)
    if not is_int(n_obstacles) or n_obstacles < 1:
        raise ValueError(f"n_obstacles must be an int >= 1, got {n_obstacles!r}")
    fast_traffic = checked_flag("fast_traffic", fast_traffic)
    env = adapted_class(ENV_CLASSES[highway_id])(config=config, render_mode=render_mode, **kwargs)
    return HighwayAdapter(env, highway_id, n_obstacles, fast_traffic)


def highway_id_of(env: gym.Env) -> str:
    """The adapter's key of ``env``: its spec's id, else its class's (a supported highway-env id, or a suite
    family's ``ID``); ``ValueError`` otherwise."""
    spec_id = getattr(getattr(env, "spec", None), "id", None)
    if spec_id in PROFILES:
        return spec_id
    base = getattr(env, "unwrapped", env)
    for highway_id, cls in ENV_CLASSES.items():
        if type(base) is cls or type(base) is adapted_class(cls):
            return highway_id
    raise ValueError(f"bimp.envs.wrap does not support {spec_id or type(base).__name__!r}; supported highway-env "
                     f"ids: {list(SUPPORTED)}")


def wrap(env: gym.Env, n_obstacles: int = N_OBSTACLES, fast_traffic: bool = True) -> "HighwayAdapter":
    """``env`` (``gym.make(ID, config=...)`` of a supported highway-env id) as a bimp env: see the module docstring.
    The config keys the env was given (those differing from its class's defaults) carry over; ``ValueError`` for an
    unsupported id or a config the adapter cannot honour."""
    if isinstance(env, HighwayAdapter):
        return env
    highway_id = highway_id_of(env)
    base = env.unwrapped
    defaults = ENV_CLASSES[highway_id].default_config()
    given = {k: v for k, v in base.config.items() if k != "offscreen_rendering" and defaults.get(k, object()) != v}
    return make(highway_id, given, render_mode=base.render_mode, n_obstacles=n_obstacles, fast_traffic=fast_traffic)


def entry_name(highway_id: str) -> str:
    """The name of ``highway_id``'s entry point in this module (``make_highway_v0``): what the scenario table
    registers as ``bimp.envs.highway.adapter:<name>``."""
    return "make_" + highway_id.replace("-", "_")


def _entry(highway_id: str):
    def make_env(config: Mapping | None = None, render_mode: str | None = None, n_obstacles: int = N_OBSTACLES,
                 fast_traffic: bool = True, **kwargs) -> "HighwayAdapter":
        return make(highway_id, config, render_mode, n_obstacles, fast_traffic, **kwargs)

    make_env.__name__ = make_env.__qualname__ = entry_name(highway_id)
    make_env.__doc__ = f"``bimp/{highway_id}``: :func:`make` of {highway_id!r}."
    return make_env


# The registered entry points (envs/__init__.py): one per id, "bimp.envs.highway.adapter:make_highway_v0" ...
make_highway_v0 = _entry("highway-v0")
make_highway_fast_v0 = _entry("highway-fast-v0")
make_merge_v0 = _entry("merge-v0")
make_exit_v0 = _entry("exit-v0")
make_roundabout_v0 = _entry("roundabout-v0")
make_two_way_v0 = _entry("two-way-v0")
make_u_turn_v0 = _entry("u-turn-v0")
make_racetrack_v0 = _entry("racetrack-v0")
make_intersection_v0 = _entry("intersection-v0")
# The families' entry points, made from the table (a new family writes none): make_stalled_vehicle_v0 ...
for _family in FAMILIES.values():
    globals()[entry_name(_family.ID)] = _entry(_family.ID)


class HighwayAdapter(gym.Wrapper):
    """A highway-env env (an instance of an adapted class) as a bimp env; see the module docstring."""

    def __init__(self, env: gym.Env, highway_id: str, n_obstacles: int = N_OBSTACLES, fast_traffic: bool = True):
        super().__init__(env)
        self.highway_id, self.profile, self.n_obstacles = highway_id, PROFILES[highway_id], int(n_obstacles)
        self.fast_traffic = fast_traffic
        self._start()  # highway-env's __init__ has reset the env: the scene exists before the first reset
        self.observation_space = spaces.Box(-OBS_BOUND, OBS_BOUND, shape=(self.scene.obs_dim,), dtype=np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)

    @property
    def scene(self) -> Scene:
        return self.env.unwrapped.scene

    # --- episode ---------------------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        options = dict(options or {})
        if "config" in options:  # highway-env's per-reset configure: held to what the adapter can honour
            options["config"] = adapter_config(self.highway_id, options["config"], self.env.unwrapped.config)
        _, info = self.env.reset(seed=seed, options=options or None)
        self._start()
        obs, safety = self._measure()
        return obs, {**info, **safety}

    def _start(self) -> None:
        base = self.env.unwrapped
        if self.fast_traffic:  # the road highway-env's reset built, on the fast core (bimp.envs.traffic)
            make_fast_if_known(base.road)
        # What bimp's evaluation records as the scenario's definition (as the paper's envs publish it): the env's
        # own draws where it makes some (a suite family's, drawn at this reset), else none; highway-env's config as
        # options (every key but rendering: a family's difficulty and ranges too); the behaviour layer's rule.
        base.PARAMS, base.drawn_params = {}, dict(getattr(base, "drawn_params", None) or {})
        base.OPTIONS = {k: (v,) for k, v in base.config.items() if k not in _VIEW_KEYS}
        base.BEHAVIOUR = BehaviourRule.current(self.profile.target_speed, self.n_obstacles, self.profile)
        self.dt = 1.0 / base.config["policy_frequency"]
        self.behaviour = Behaviour(base, self.profile.target_speed, self.profile.drive_on, self.profile.overtake,
                                   self.profile.junction, self.profile.gap_plan)
        self.last_input, self.prev_input = np.zeros(2), np.zeros(2)
        self.progress = 0.0
        self._speeds: dict[int, float] = {}
        self._accels: dict[int, float] = {}
        self._ended = False
        self._routes, self._shifted = RouteCache(), (None, 0.0, None)
        check_steering_reach(base.road.network, getattr(base.vehicle, "route", None) or self.behaviour.route,
                             base.action_type.steering_range, VEHICLE_LENGTH, self.highway_id)
        self.behaviour.decide(0.0)
        self._publish()
        self._ev_s = float(self.scene.road.project(np.array(base.vehicle.position, float)).s)  # as _measure sets it

    def step(self, action):
        if self._ended:
            raise ResetNeeded("step() after the episode terminated (collision, off the road or highway-env's own "
                              "end): call reset() first")
        action = checked_action(action)
        base, road_before = self.env.unwrapped, self.scene.road
        ev = base.vehicle
        before = np.array(ev.position, float)
        self.prev_input, self.last_input = self.last_input, self.scene.to_physical(action)
        self._speeds = {id(v): float(v.speed) for v in self._others()}
        _, reward, terminated, truncated, info = self.env.step(np.clip(action, -1, 1).astype(np.float32))
        self._accels = {id(v): (float(v.speed) - self._speeds[id(v)]) / self.dt
                        for v in self._others() if id(v) in self._speeds}
        self.behaviour.decide(self.dt)
        self._publish()
        obs, safety = self._measure((road_before, before))
        # highway-env ends an episode off the road by its on_road (racetrack-v0 does by default), which counts the
        # seam between two lanes of one road as off it; bimp's offroad (lanes.off_lanes) decides instead.
        seam = not ev.on_road and not ev.crashed and not safety["offroad"]
        terminated = bool((terminated and not seam) or safety["collision"] or safety["offroad"] or bool(safety["goal"]))
        self._ended = terminated
        return obs, float(reward), terminated, bool(truncated), {**info, **safety}

    def render(self):
        """highway-env's own frame, in ``rgb_array`` mode with the lines a caller set in ``env.unwrapped.overlay``
        (an agent's plan: :mod:`bimp.envs.overlay`) drawn under the vehicles."""
        frame = self.env.render()
        drawn = draw_lines(self.env.unwrapped) if frame is not None else None
        return frame if drawn is None else drawn

    # --- the scene -------------------------------------------------------------------------------------------
    def _publish(self) -> None:
        base = self.env.unwrapped
        ev = base.vehicle
        route = getattr(ev, "route", None) or self.behaviour.route
        self._lane_on_route = self._route_lane(ev, route)  # the reference's lane (_abreast) reads it too
        road, at = self._routes.get(base.road.network, self._lane_on_route, ev.position, route)
        # Headings are continuous along the route; shift them by whole turns to the EV's own (unwrapped) heading.
        turns = float(np.round((ev.heading - float(road.heading[at])) / (2 * np.pi)))
        if road is not self._shifted[0] or turns != self._shifted[1]:
            shifted = road if not turns else Route(xy=road.xy, s=road.s, heading=road.heading + 2 * np.pi * turns,
                                                   curvature=road.curvature, left=road.left, right=road.right)
            self._shifted = (road, turns, shifted)
        p = self.profile
        base.scene = Scene(road=self._shifted[2], bounds=p.bounds, dt=self.dt, vehicle_length=VEHICLE_LENGTH,
                           vehicle_width=VEHICLE_WIDTH, actuator_accel=tuple(base.action_type.acceleration_range),
                           actuator_steer=tuple(base.action_type.steering_range), n_obstacles=self.n_obstacles,
                           lane_path=p.lane_path, on_lanes=on_lanes_of(base.road.network), edge_guard=True)

    def _route_lane(self, ev, route):
        """The EV's lane on its route: highway-env's closest lane, unless that lane's road is off the route and a
        lane of the route holds the EV (at a junction: a roundabout's ring beside the entry the EV is on); then the
        route's lane nearest to the EV's centre."""
        index = ev.lane_index
        if not route or route_from(route, index) is not None:
            return index
        graph, position = self.env.unwrapped.road.network.graph, np.array(ev.position, float)
        best, least = index, np.inf
        for _from, _to, _ in route:
            for k, lane in enumerate(graph.get(_from, {}).get(_to, [])):
                s, lat = coordinates(lane, position)
                if lane.on_lane(position, s, lat) and abs(lat) < least:
                    best, least = (_from, _to, k), abs(lat)
        return best

    def _goal(self) -> bool | None:
        """highway-env's goal where its env has one (``info["goal"]``, None on the envs without one; success needs
        it where there is one, else the time limit):
        exit-v0's exit lane or road reached (highway-env's ``_is_success``), intersection-v0's ``has_arrived``
        (crossed, on the exit road),
        merge-v0's end of the road (x > 370 m, where highway-env ends it) and, on roundabout-v0, the last road of
        the EV's route reached (the roundabout left); past exit's and roundabout's the EV would run off the end of
        the network, so the adapter ends the episode there. A suite family with a goal says it by its
        ``goal_reached()`` (two-way-overtake: the slow vehicle passed)."""
        base = self.env.unwrapped
        if hasattr(base, "goal_reached"):
            return bool(base.goal_reached())
        if self.highway_id == "exit-v0":  # highway-env's own: in the exit lane (it leads only to the exit) or beyond
            return bool(base._is_success())
        if self.highway_id == "intersection-v0":
            return bool(base.has_arrived(base.vehicle))
        if self.highway_id == "merge-v0":
            return bool(base.vehicle.position[0] > 370)
        if self.highway_id == "roundabout-v0":
            route = getattr(base.vehicle, "route", None)
            return bool(route and base.vehicle.lane_index[:2] == route[-1][:2])
        return None

    def _others(self) -> list:
        base = self.env.unwrapped
        return [v for v in base.road.vehicles if v is not base.vehicle] + list(base.road.objects)

    def _rows(self) -> tuple[np.ndarray, np.ndarray, list]:
        """Every other vehicle and road object as an OV row ``(N, 6)``, nearest first (by centre distance),
        highway-env's crash flag of each ``(N,)`` (``crashed``, or ``hit`` for an object it lets vehicles pass
        through) and the vehicles and objects themselves, in the same order."""
        ev = self.env.unwrapped.vehicle
        others = self._others()
        rows = np.array([[1.0, *v.position, v.heading, v.speed, self._accels.get(id(v), 0.0)]
                         for v in others]).reshape(-1, len(OV_FIELDS))
        crashed = np.array([bool(v.crashed or getattr(v, "hit", False)) for v in others], bool)
        distance = np.hypot(*(rows[:, 1:3] - ev.position).T) if len(rows) else np.zeros(0)
        order = np.argsort(distance, kind="stable")
        return rows[order], crashed[order], [others[i] for i in order]

    def reference(self) -> np.ndarray:
        """``[v_ref m/s, a_ref m/s^2, l_ref m]`` (module docstring)."""
        return self._reference(self.scene.road.project(np.stack([self._ev_state()[:2], self._abreast()])))

    def _abreast(self) -> np.ndarray:
        """The point ``(2,)`` of MOBIL's target lane's centre abreast of the EV. On a junction road
        (:attr:`Profile.junction`) the route blends across the gaps between lanes (``lanes.smooth_bridges``) and so
        lies off their centres there: the point is the route's own abreast of the EV moved by the target lane's
        offset from the EV's lane on its route (0 without a lane change); a target lane on another road (highway-env's
        driver turns to the next road a little before this one ends) is the EV's own. With the profile's
        ``lane_path`` (exit-v0): where the gap plan holds the EV 2 s on, while it has one (``GapDriver.lead_point``)."""
        ev = self.env.unwrapped.vehicle
        network = self.env.unwrapped.road.network
        index = self.behaviour.target_lane_index

        def centre(lane_index) -> np.ndarray:
            lane = network.get_lane(lane_index)
            return np.asarray(lane.position(coordinates(lane, ev.position)[0], 0.0), float)

        lead = self.behaviour.shadow.lead_point() if self.profile.lane_path else None  # lane_path: a gap plan
        if lead is not None:
            return lead
        if not self.profile.junction:
            return centre(index)
        own = self._lane_on_route
        if tuple(index[:2]) != tuple(own[:2]):
            index = own
        road = self.scene.road
        return road.position(road.project(np.asarray(ev.position, float)).s, 0.0) + centre(index) - centre(own)

    def _reference(self, p) -> np.ndarray:
        """:meth:`reference` from the projections ``p`` of the EV's position (first) and :meth:`_abreast` (second)."""
        half = self.scene.vehicle_width / 2
        e_left, e_right = float(p.left[0]), float(p.right[0])
        l_ref = float(np.clip(p.l[1], e_left + half, e_right - half)) if e_right - e_left > 2 * half else 0.0
        speed = max(float(self.env.unwrapped.vehicle.speed), 0.0)
        a_ref = self.behaviour.action["acceleration"]
        if np.isfinite(self.profile.lateral_accel):
            a_ref = min(a_ref, curve_acceleration(self.scene.road, float(p.s[0]), speed, self.profile.lateral_accel))
        return np.array([speed, float(np.clip(a_ref, *self.scene.bounds.accel)), l_ref])

    def _ev_state(self) -> np.ndarray:
        ev = self.env.unwrapped.vehicle
        return np.array([*ev.position, ev.heading, ev.speed], float)

    def _measure(self, stepped: tuple[Route, np.ndarray] | None = None) -> tuple[np.ndarray, dict]:
        """The observation and bimp's safety ``info`` of the current state, from one reading of the traffic and one
        projection on the route of every point they need: the EV, the reference lane abreast, the EV's body corners
        and the OVs in the slots (rows ``0``, ``1``, ``2:6``, ``6:``). After a step, ``stepped``: the road before it
        and the EV's position then, to add the step's progress along that road."""
        rows, crashed, others = self._rows()
        base = self.env.unwrapped
        if self.profile.junction:  # the slots' paths along their lanes (bimp.envs.highway.prediction)
            base.scene = dataclasses.replace(base.scene, ov_paths=lane_paths(
                base.road.network, others, list(rows[:self.n_obstacles, 5]), self.n_obstacles, self.dt))
        state = self._ev_state()
        corners = body_corners(state[:2], state[2], VEHICLE_LENGTH, VEHICLE_WIDTH)
        p = self.scene.road.project(np.vstack([state[None, :2], self._abreast()[None], corners,
                                               rows[:self.n_obstacles, 1:3]]))
        if stepped is not None:
            road_before, before = stepped
            if road_before is self.scene.road and abs(float(p.s[0]) - self._ev_s) < PROGRESS_WINDOW / 2:
                self.progress += float(p.s[0]) - self._ev_s  # the route kept: the EV's arc lengths on it
            else:  # on a window of the road before about the EV (an EV far off it projects on any pass near it)
                local = road_before.window(self._ev_s - PROGRESS_WINDOW / 4, int(PROGRESS_WINDOW) + 1, 1.0)
                s_before, s_after = local.project(np.stack([before, state[:2]])).s
                self.progress += float(s_after - s_before)
        self._ev_s = float(p.s[0])  # where the next step's progress starts
        ref = self._reference(p)
        return self._observe(state, rows, ref), self._safety(state, rows, ref, crashed, p)

    def _observe(self, state: np.ndarray, rows: np.ndarray, ref: np.ndarray) -> np.ndarray:
        ovs = np.zeros((self.n_obstacles, len(OV_FIELDS)))
        ovs[:min(len(rows), self.n_obstacles)] = rows[:self.n_obstacles]
        obs = join_obs(state, self.last_input, ovs, ref)
        return np.clip(obs, -OBS_BOUND, OBS_BOUND).astype(np.float32)

    def _safety(self, state: np.ndarray, rows: np.ndarray, ref: np.ndarray, crashed: np.ndarray, p) -> dict:
        base, scene = self.env.unwrapped, self.scene
        ev, network = base.vehicle, base.road.network
        # Footprint gaps of the slots, of any vehicle near enough to touch (centres within the two half-diagonals)
        # and, once highway-env has crashed the EV, of all (the contact may be one it pushed apart).
        gaps_all = np.full(len(rows), np.inf)
        near = np.hypot(*(rows[:, 1:3] - state[:2]).T) <= np.hypot(VEHICLE_LENGTH, VEHICLE_WIDTH) + 1e-6
        near[:self.n_obstacles] = True
        if ev.crashed:
            near[:] = True
        if near.any():
            gaps_all[near] = scene.ov_gaps(state, rows[near])
        gaps = np.full(self.n_obstacles, np.inf)
        gaps[:min(len(rows), self.n_obstacles)] = gaps_all[:self.n_obstacles]
        edge = float(corner_edge_margin(Projection(*(field[2:6] for field in p))))
        e = Projection(*(field[0] for field in p))
        slots = rows[:self.n_obstacles]
        if len(slots):
            o = Projection(*(field[6:] for field in p))
            ahead = (o.s > e.s) & (np.abs(o.l - e.l) < scene.vehicle_width + 0.5)
            closing = ev.speed - slots[:, 4] * np.cos(slots[:, 3] - o.heading)
            ttc = np.where(ahead & (closing > 1e-6), np.maximum(gaps[:len(slots)], 0.0) / np.maximum(closing, 1e-6),
                           np.inf)
        else:
            ttc = np.array([np.inf])
        b, u = scene.bounds, self.last_input
        constraints = constraint_values(b, u, self.prev_input, gaps, edge)
        # The closed-loop score's per-step facts. The OV touched: the least footprint gap <= 0, else, where
        # highway-env crashed the EV (its impact may have pushed the pair apart), the nearest vehicle it flags
        # crashed (any vehicle, should it flag none). The limit: the EV's lane's (highway-env's IDM caps its target
        # speed at it), the profile's free-road target where a lane has none. The lateral speed: across the route
        # at the EV's projection (the slip angle left out).
        limit = getattr(getattr(ev, "lane", None), "speed_limit", None)
        flagged = (crashed if crashed.any() else np.ones_like(crashed)) if ev.crashed else None
        attribution = attribution_info(state, rows, gaps_all,
                                       ev_lateral_speed=float(ev.speed * np.sin(ev.heading - e.heading)),
                                       speed_limit=self.profile.target_speed if limit is None else limit,
                                       crashed=flagged)
        return {
            "collision": bool(ev.crashed or (len(gaps_all) and gaps_all.min() <= 0.0)),
            "offroad": bool((not ev.on_road and off_lanes(network, state[None, :2], SEAM_MARGIN, besides=ev.lane))
                            or (edge < 0.0 and off_lanes(network, body_corners(state[:2], state[2], VEHICLE_LENGTH,
                                                                               VEHICLE_WIDTH), JUNCTION_MARGIN))),
            "ov_distance": gaps.tolist(), "edge_distance": edge,
            "ttc": float(ttc.min()), "s": self.progress, "reference": ref.tolist(),
            "lateral_error": float(e.l - ref[2]), "speed_error": float(ev.speed - self.profile.target_speed),
            "longitudinal_speed": float(ev.speed * np.cos(ev.heading - e.heading)), "input": u.tolist(),
            "constraints": constraints, "ahead_of_ov1": None, "target_lane": list(self.behaviour.target_lane_index),
            "goal": self._goal(), **attribution,
        }
