"""The behaviour layer of a wrapped highway-env env: highway-env's own driver decides, as it decides for its traffic.

A *shadow* :class:`highway_env.vehicle.behavior.IDMVehicle` is synced to the EV's state at every step (never
simulated, never in the road's vehicle list) and asked what highway-env's driver would do there:

- route: the EV's route (its destination in exit, roundabout, u-turn and intersection; on the other roads the lane
  graph's own choice, ``RoadNetwork.next_lane``), followed by ``follow_road``;
- lane: MOBIL (``change_lane_policy`` / ``mobil``, politeness and thresholds as highway-env's traffic has them) on
  multi-lane roads, never into a lane that oncoming traffic drives on (:class:`ShadowDriver`) but where the id's
  profile lets it overtake there (the suite's two-way-overtake: :class:`OvertakeDriver`); on exit-v0 a plan
  through the gaps of the lanes between leads into the exit lane (:class:`GapDriver`), and the exit is taken only
  from that lane, else missed (:class:`DriveOnDriver`); an ending lane is
  left when highway-env's driver leaves it (its route moves to the next road's
  nearest lane at the end, and MOBIL's incentive comes from the lane's end as an obstacle only where highway-env
  models one);
- speed: IDM (``acceleration``) towards the target speed of the env's config (the adapter's table), capped by the
  lane's speed limit as IDM caps it, behind the vehicle ahead in the EV's lane and, during a lane change, in the
  target lane too;
- steering: highway-env's lane-following controller (``steering_control``) towards the target lane.

:meth:`Behaviour.decide` returns the shadow's ``{"acceleration", "steering"}`` (what ``IDMVehicle.act`` commands)
and keeps its target lane, which the adapter turns into the reference. For the decision the EV's slot in the
road's vehicle list holds the shadow, so the EV is not its own neighbour; the list is restored at once.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass

import numpy as np
from highway_env.vehicle.behavior import IDMVehicle

from bimp.configs import neutral_values
from bimp.envs.highway.gaps import GapPlan, GapSearch, plan_gaps
from bimp.envs.highway.junction import Yielding, yield_acceleration
from bimp.envs.highway.lanes import coordinates, goes_on_beside, needed_lane
from bimp.envs.road import Route

# Bumped whenever the adapter or the behaviour layer changes what an episode does, so that records made before are
# another scenario definition, never resumed as this one's. 2: routes that skip non-adjacent lane joins, the EV that
# never reverses, MOBIL that never travels in an oncoming lane, the traffic's IDM parameters restored per reset.
# 3: short gaps between lanes that go on straight (roundabout-v0's entries) bridged instead of ending the route.
VERSION = 3
_IDM_KEYS = ("ACC_MAX", "COMFORT_ACC_MAX", "COMFORT_ACC_MIN", "DISTANCE_WANTED", "TIME_WANTED", "DELTA", "POLITENESS",
             "LANE_CHANGE_MIN_ACC_GAIN", "LANE_CHANGE_MAX_BRAKING_IMPOSED", "LANE_CHANGE_DELAY")


@dataclass(frozen=True)
class BehaviourRule:
    """The behaviour layer's rule as an evaluation arm records it (``env.unwrapped.BEHAVIOUR``, as the paper's envs
    publish theirs): the free-road ``target_speed`` [m/s], highway-env's IDM and MOBIL parameters as its
    ``IDMVehicle`` class holds them now (intersection-v0 changes some for its own traffic), the adapter's
    ``n_obstacles``, its per-id ``profile`` (planning bounds, actuator range, target speed, duration) and the
    code's ``version`` (:data:`VERSION`: bumped whenever the adapter or this layer changes what an episode does).
    A changed rule is a changed scenario."""

    target_speed: float
    idm: tuple
    n_obstacles: int
    profile: str = ""
    version: int = VERSION

    @classmethod
    def current(cls, target_speed: float, n_obstacles: int, profile=None) -> "BehaviourRule":
        """The rule now; ``profile``: the adapter's per-id numbers (planning bounds, actuator range), recorded too,
        less its fields added later at their neutral value (:func:`bimp.configs.added_field`: the rule of the
        records made before them)."""
        neutral = neutral_values(type(profile)) if profile is not None else {}
        numbers = tuple(sorted((k, v) for k, v in dataclasses.asdict(profile).items()
                               if k not in neutral or v != neutral[k])) if profile is not None else ()
        return cls(float(target_speed), tuple((k, float(getattr(IDMVehicle, k))) for k in _IDM_KEYS), n_obstacles,
                   repr(numbers), VERSION)


class ShadowDriver(IDMVehicle):
    """highway-env's IDM + MOBIL driver, except that MOBIL never picks a lane that oncoming traffic drives on as a
    lane to travel in. two-way-v0 draws its left lane twice, once per direction (``("a", "b", 0)`` and
    ``("b", "a", 0)``, the same centreline): highway-env's MOBIL sees no vehicle on the former (the oncoming ones are
    on the latter), moved the EV into it, and the EV then met the oncoming traffic head on and stopped there (EnKTS,
    development seeds). Overtaking in the oncoming lane is a decision of its own (the suite's two-way-overtake)."""

    clock = 0.0  # s since the episode began (Behaviour.decide advances it)

    def mobil(self, lane_index) -> bool:
        return not carries_oncoming_traffic(self.road.network, lane_index) and super().mobil(lane_index)


class OvertakeDriver(ShadowDriver):
    """:class:`ShadowDriver` that overtakes a slower leader through the lane of oncoming traffic beside its own, as a
    human driver on a two-way road does (the suite's ``two-way-overtake``):

    - **pull out** when the leader in its lane drives at least :attr:`SLOWER` m/s below the target speed, within
      :attr:`PASS_RANGE` m, and every oncoming vehicle ahead is at least :attr:`PASS_GAP` s away at the closing
      speed: a fixed critical time gap, as gap-acceptance models of human passing take one. It does not check that
      the pass fits that gap, so some gaps it accepts are too short: the benchmark's planners have to judge;
    - **withdraw** a pull-out while still in its own lane once the nearest oncoming vehicle is less than
      :attr:`PASS_GAP` - :attr:`HESITATION` s away (the gap it took is gone before the EV moved over: a planner that
      did not follow);
    - **fall back** out in the oncoming lane when the pass no longer fits: the time to meet the nearest oncoming
      vehicle is less than :func:`pass_time` to get the return gap ahead of the leader (accelerating at IDM's
      comfortable ``COMFORT_ACC_MAX`` up to the target speed) plus :attr:`ABORT_MARGIN` s. The return gap is the
      least lead at which the leader's IDM brakes at most ``LANE_CHANGE_MAX_BRAKING_IMPOSED`` for the EV
      (:meth:`return_gap`: about 16-25 m at hard's speeds). IDM then drives behind the leader as if it were in the
      same lane;
    - **return** to its own lane once past the leader or when falling back, checked at every step while in the
      oncoming lane (not every ``LANE_CHANGE_DELAY``): where the new follower brakes at most
      ``LANE_CHANGE_MAX_BRAKING_IMPOSED`` and the EV itself too (falling back: up to ``ACC_MAX``).

    In the oncoming lane IDM ignores the oncoming vehicles (highway-env's IDM would brake head-on for them, and
    behind the leader's tail that only strands it there): the fall-back rule answers them. The oncoming traffic's
    own IDM brakes for an EV in its lane, which is highway-env's and not the reference's doing."""

    PASS_GAP = 8.0  # s
    SLOWER = 2.0  # m/s
    PASS_RANGE = 60.0  # m, centre to centre
    ABORT_MARGIN = 3.0  # s: the return's lane change (about 2 s at the planning bounds) and a step's decision
    HESITATION = 2.0  # s: how far below the critical gap a pull-out not yet begun is kept (no flicker at the gap)

    def mobil(self, lane_index) -> bool:
        if carries_oncoming_traffic(self.road.network, lane_index):
            return bool(self._slow_leader(self.lane_index, self.PASS_RANGE) is not None
                        and self._time_to_meet() >= self.PASS_GAP)
        return super().mobil(lane_index)

    def change_lane_policy(self) -> None:
        network = self.road.network
        if self.lane_index != self.target_lane_index and carries_oncoming_traffic(network, self.target_lane_index):
            if (self._time_to_meet() < self.PASS_GAP - self.HESITATION
                    or self._slow_leader(self.lane_index, self.PASS_RANGE) is None):
                self.target_lane_index = self.lane_index  # the gap taken is gone before the EV moved over
            return
        if carries_oncoming_traffic(network, self.lane_index):
            home = self._home_lane()
            if self.target_lane_index == self.lane_index != home and self._may_return(home):
                self.target_lane_index = home
            return
        super().change_lane_policy()

    def acceleration(self, ego_vehicle, front_vehicle=None, rear_vehicle=None) -> float:
        if ego_vehicle is self and front_vehicle is not None and _oncoming(self, front_vehicle):
            front_vehicle = self._slow_leader(self._home_lane()) if self._must_fall_back() else None
        return super().acceleration(ego_vehicle, front_vehicle, rear_vehicle)

    def return_gap(self, leader) -> float:
        """The least lead [m, centre to centre] on ``leader`` at which its IDM, holding its target speed, brakes at
        most ``LANE_CHANGE_MAX_BRAKING_IMPOSED`` for the EV at today's speeds: IDM's ``-COMFORT_ACC_MAX (s* / d)^2``
        at the desired gap ``s*``."""
        return float(self.desired_gap(leader, self) *
                     np.sqrt(self.COMFORT_ACC_MAX / self.LANE_CHANGE_MAX_BRAKING_IMPOSED))

    def _home_lane(self):
        """The lane beside the current one that oncoming traffic does not drive on (the current lane if it is one)."""
        network = self.road.network
        if not carries_oncoming_traffic(network, self.lane_index):
            return self.lane_index
        return next((lane for lane in network.side_lanes(self.lane_index)
                     if not carries_oncoming_traffic(network, lane)), self.lane_index)

    def _slow_leader(self, lane_index, within: float = np.inf):
        """The vehicle ahead in ``lane_index`` if it drives :attr:`SLOWER` below the target speed, its centre less
        than ``within`` m ahead, else None."""
        leader, _ = self.road.neighbour_vehicles(self, lane_index)
        if leader is None or _oncoming(self, leader):
            return None
        ahead = self.lane_distance_to(leader, self.road.network.get_lane(lane_index))
        return leader if ahead < within and leader.speed < self._target() - self.SLOWER else None

    def _target(self) -> float:
        limit = getattr(self.lane, "speed_limit", None)
        return float(self.target_speed if limit is None else min(self.target_speed, limit))

    def _time_to_meet(self) -> float:
        """Seconds until the nearest oncoming vehicle ahead meets the EV at today's speeds, footprints touching;
        inf where none is ahead."""
        ahead = [(self.lane_distance_to(v), v) for v in self.road.vehicles if v is not self and _oncoming(self, v)]
        times = [(d - (self.LENGTH + v.LENGTH) / 2) / max(self.speed + v.speed, 1e-6) for d, v in ahead if d > 0]
        return max(min(times), 0.0) if times else np.inf

    def _must_fall_back(self) -> bool:
        """Out in the oncoming lane with a pass that no longer fits before the nearest oncoming vehicle (class
        doc)."""
        network = self.road.network
        if not carries_oncoming_traffic(network, self.lane_index):
            return False
        home_index = self._home_lane()
        leader = self._slow_leader(home_index)
        if leader is None:
            return False
        ahead = self.lane_distance_to(leader, network.get_lane(home_index))
        needed = pass_time(ahead + self.return_gap(leader), self.speed, leader.speed, self._target(),
                           self.COMFORT_ACC_MAX)
        return self._time_to_meet() < needed + self.ABORT_MARGIN

    def _may_return(self, lane_index) -> bool:
        """Back to its own lane ``lane_index`` from the oncoming lane: past every slower vehicle there, or falling
        back; either where the new follower brakes at most ``LANE_CHANGE_MAX_BRAKING_IMPOSED`` for the EV and the EV
        itself too (falling back: up to ``ACC_MAX``)."""
        falling_back = self._must_fall_back()
        if self._slow_leader(lane_index) is not None and not falling_back:
            return False  # the pass goes on
        preceding, following = self.road.neighbour_vehicles(self, lane_index)
        own = self.ACC_MAX if falling_back else self.LANE_CHANGE_MAX_BRAKING_IMPOSED
        return bool((following is None or
                     self.acceleration(following, self) >= -self.LANE_CHANGE_MAX_BRAKING_IMPOSED) and
                    (preceding is None or self.acceleration(self, preceding) >= -own))


def pass_time(distance: float, speed: float, leader_speed: float, top_speed: float, accel: float) -> float:
    """Seconds [s] for a vehicle at ``speed`` [m/s] accelerating at ``accel`` [m/s^2] up to ``top_speed`` to gain
    ``distance`` [m] on a leader holding ``leader_speed``; inf where it never does."""
    if distance <= 0.0:
        return 0.0
    w0 = speed - leader_speed  # the relative speed now, and at the top speed
    t1 = max(top_speed - speed, 0.0) / accel
    gained = w0 * t1 + accel * t1 ** 2 / 2
    if gained >= distance:  # within the acceleration: w0 t + a t^2 / 2 = distance
        return float((-w0 + np.sqrt(w0 ** 2 + 2 * accel * distance)) / accel)
    w1 = top_speed - leader_speed
    return float(t1 + (distance - gained) / w1) if w1 > 0.0 else np.inf


def _oncoming(vehicle, other) -> bool:
    """Whether ``other`` drives towards ``vehicle``: on the reverse road of ``vehicle``'s lane, heading against it."""
    a, b = vehicle.lane_index[:2]
    return bool(tuple(other.lane_index[:2]) == (b, a) and np.cos(other.heading - vehicle.heading) < 0.0)


class DriveOnDriver(ShadowDriver):
    """:class:`ShadowDriver` that drives on where its route's next road leaves from another lane than its own (the
    exit missed) instead of following highway-env's ``next_lane``, which then jumps to that road's nearest lane: on
    exit-v0 a 24 m chord across five lanes of traffic (highway-env's driver collided on 14 of 50 results seeds
    there). The route is dropped and the lane graph's own way on taken (:func:`bimp.envs.highway.lanes.goes_on_beside`).

    exit-v0's EV starts in the leftmost lane and highway-env's drivers never head for the exit: ``plan_route_to``
    names the start lane as the route's first (MOBIL's route branch then refuses every change). Mandatory lane
    changes towards the exit lane were tried (MOBIL's route branch towards it, from 2 to 3.5 s of travel per change
    still needed, the braking imposed allowed up to 4 or 8 m/s^2, falling in behind the next lane's leader): 0
    exits on 20 development seeds, the EV reached lane 1 to 4 of 6. The right lanes' gaps at exit-v0's density lie
    well inside IDM's desired gap (a 32 m gap at 17 m/s imposes about -20 m/s^2 on the new follower), so no
    change is ever safe by highway-env's own measure. Left out: it decided nothing."""

    def follow_road(self) -> None:
        network = self.road.network
        lane = network.get_lane(self.target_lane_index)
        if self.route and lane.after_end(self.position):
            following = network.next_lane(self.target_lane_index, route=list(self.route), position=self.position)
            if goes_on_beside(network, self.target_lane_index, following):
                self.route = None  # missed: the lane graph's own way on
        super().follow_road()


class GapDriver(DriveOnDriver):
    """:class:`DriveOnDriver` that plans its way into the lane its route needs (exit-v0's exit lane, six lanes to
    the right of the start) through the gaps of the lanes between (:func:`bimp.envs.highway.gaps.plan_gaps`),
    where MOBIL waits for a gap its own rule accepts and at exit-v0's density none comes. Replanned every
    lattice step (:attr:`SEARCH`, at the target speed as its top speed), its first step driven until then: the
    lane change begun or not (MOBIL's target lane replaced), the acceleration (IDM's replaced). Where the
    lattice finds no way in (or the EV is past it, or off its route), highway-env's driver decides, MOBIL
    included. The plan's top speed is the target speed: exit-v0's lane speed limits (26 m/s in the left lane,
    3.4 m/s less per lane to the right) are its traffic's speeds, and an EV held to them could not reach the
    exit within the episode.
    """

    SEARCH = GapSearch()
    plan: GapPlan | None = None
    _goal_lane = None  # the needed lane, where the plan's place across the lanes is measured (lead_point)
    _next_plan = 0.0  # s of :attr:`ShadowDriver.clock`: MOBIL's own timer is left to MOBIL, which needs it

    def change_lane_policy(self) -> None:
        if self.clock >= self._next_plan - 1e-9:
            self._next_plan = self.clock + self.SEARCH.step
            self.plan, self._plan_lane = self._plan()
        if self.plan is None:
            super().change_lane_policy()
            return
        road = self.target_lane_index[:2]
        if self._plan_lane < len(self.road.network.graph[road[0]][road[1]]):  # the needed lane may begin further on
            self.target_lane_index = (*road, self._plan_lane)

    def acceleration(self, ego_vehicle, front_vehicle=None, rear_vehicle=None) -> float:
        if ego_vehicle is self and self.plan is not None:
            return self.plan.accel
        return super().acceleration(ego_vehicle, front_vehicle, rear_vehicle)

    def _plan(self) -> tuple[GapPlan | None, int]:
        """The lattice's plan from here and the number of the lane its first step drives to (the one the EV is in,
        or the next towards the needed lane): (None, -1) where there is none."""
        network = self.road.network
        goal_index = needed_lane(network, [self.lane_index, *self.route], self.lane_index[2]) if self.route else None
        if goal_index is None:
            return None, -1
        goal = network.get_lane(goal_index)
        self._goal_lane = (goal, goal_index[2])
        s, lat = coordinates(goal, self.position)
        window = (0.0, goal.length - self.LENGTH)
        if s >= window[1]:
            return None, -1  # before, in the needed lane, the lattice drives on at speed (no braking to its limit)
        width, k = goal.width_at(s), goal_index[2]
        frac = k + lat / width
        toward = int(np.sign(k - frac)) or 1
        lane = int(np.floor(frac + 0.125)) if toward > 0 else int(np.ceil(frac - 0.125))
        cs = self.SEARCH.change_steps
        phase = int(np.clip(np.round(abs(frac - lane) * cs), 0, cs - 1))
        rows = []
        for other in self.road.vehicles:
            if other is self or np.cos(other.heading - self.heading) <= 0:
                continue
            so, lo = coordinates(goal, other.position)
            rows.append((np.round(k + lo / width), so, other.speed))
        search = dataclasses.replace(self.SEARCH, top_speed=max(float(self.target_speed), 1e-3))
        plan = plan_gaps(search, s, self.speed, lane, phase, k, window, np.array(rows))
        return plan, lane + (toward if plan is not None and plan.change else 0)

    def lead_point(self) -> np.ndarray | None:
        """The point ``(2,)`` abreast of the EV where the plan holds it :attr:`GapSearch.lookahead` s after it was
        made (1.5-2 s from now: the plan is remade every lattice step)
        (:attr:`GapPlan.ahead`: in the next lane but one while the plan changes lanes back to back), None without a
        plan. MOBIL's target lane names the next lane only, and a reference that stops at each lane's centre
        slowed the planners to about 4 s a lane: exit-v0's six lanes took longer than the episode."""
        if self.plan is None or self._goal_lane is None:
            return None
        goal, k = self._goal_lane
        s = coordinates(goal, self.position)[0]
        return np.asarray(goal.position(s, (self.plan.ahead - k) * goal.width_at(s)), float)


def carries_oncoming_traffic(network, lane_index) -> bool:
    """Whether a lane of the opposite direction between the same nodes runs along ``lane_index``'s centreline (its
    start on the lane's end, within half a lane width)."""
    _from, _to, _ = lane_index
    lane = network.get_lane(lane_index)
    start, end = lane.position(0.0, 0.0), lane.position(lane.length, 0.0)
    return any(np.linalg.norm(other.position(0.0, 0.0) - end) < lane.width_at(0.0) / 2
               and np.linalg.norm(other.position(other.length, 0.0) - start) < lane.width_at(0.0) / 2
               for other in network.graph.get(_to, {}).get(_from, []))


class Behaviour:
    """highway-env's IDM + MOBIL driver shadowing the EV of ``env`` (a highway-env env). ``target_speed`` [m/s]:
    the speed it aims for on a free road; ``drive_on``: drive on where the route's next road leaves from another
    lane (:class:`DriveOnDriver`); ``overtake``: overtake through the oncoming lane (:class:`OvertakeDriver`);
    ``yields``: yield at junctions by gap acceptance (:mod:`bimp.envs.highway.junction`): the acceleration is then
    the lesser of IDM's and IDM's behind a stopped vehicle short of the conflict. :attr:`own_action` keeps
    highway-env's driver's command without the yielding (what the ``idm`` baseline drives by default)."""

    def __init__(self, env, target_speed: float, drive_on: bool = False, overtake: bool = False,
                 yields: bool = False, gap_plan: bool = False):
        if drive_on and overtake:
            raise ValueError("a behaviour layer drives on past a missed exit (drive_on) or overtakes in the oncoming "
                             "lane (overtake), not both")
        self.env, self.target_speed = env, float(target_speed)
        ev = env.vehicle
        driver = (GapDriver if gap_plan else DriveOnDriver if drive_on else OvertakeDriver if overtake
                  else ShadowDriver)
        self.shadow = driver(env.road, np.array(ev.position, float), heading=ev.heading, speed=ev.speed,
                                 target_lane_index=ev.lane_index, target_speed=self.target_speed,
                                 route=copy.deepcopy(getattr(ev, "route", None)) or None, timer=0.0)
        self.yielding = Yielding() if yields else None
        self.action = {"acceleration": 0.0, "steering": 0.0}
        self.own_action, self.yield_distance = dict(self.action), None

    @property
    def target_lane_index(self):
        return self.shadow.target_lane_index

    @property
    def route(self):
        """The shadow's route (lane indices ahead; None where the EV has none): what the adapter's road follows."""
        return self.shadow.route

    def decide(self, dt: float = 0.0) -> dict:
        """Sync the shadow to the EV (``dt`` [s] since the last decision advances MOBIL's decision timer) and return
        highway-env's driver's ``{"acceleration" m/s^2, "steering" rad}`` there."""
        env, shadow = self.env, self.shadow
        ev = env.vehicle
        shadow.position = np.array(ev.position, float)
        shadow.heading, shadow.speed = float(ev.heading), float(ev.speed)
        shadow.lane_index, shadow.lane = ev.lane_index, ev.lane
        shadow.timer += dt
        shadow.clock += dt
        vehicles = env.road.vehicles
        slot = next((i for i, v in enumerate(vehicles) if v is ev), None)
        if slot is not None:
            vehicles[slot] = shadow
        try:
            shadow.act()
        finally:
            if slot is not None:
                vehicles[slot] = ev
        self.own_action = {"acceleration": float(shadow.action["acceleration"]),
                           "steering": float(shadow.action["steering"])}
        self.action = dict(self.own_action)
        others = [v for v in vehicles if v is not ev]
        self.yield_distance = self.yielding.stop_distance(shadow, others) if self.yielding else None
        if self.yield_distance is not None:
            self.action["acceleration"] = min(self.action["acceleration"],
                                              yield_acceleration(shadow, self.yield_distance))
        return self.action


CURVE_WINDOW = 5.0  # m: a curve's curvature is the route's heading change over this (a kink reads as a curve)
CURVE_LOOKAHEAD = 6.0  # s: how far ahead, at the EV's speed (at least 20 m), curves are braked for
CURVE_REACTION = 1.0  # s: the least distance to brake over is the EV's speed times this


def curve_acceleration(route: Route, s: float, speed: float, lateral_accel: float) -> float:
    """The least acceleration [m/s^2] over the route ahead of arc length ``s`` [m] that brings ``speed`` [m/s] to
    each point's curve speed ``sqrt(lateral_accel / |kappa|)`` by the time the EV reaches it,
    ``(v_c^2 - v^2) / 2 d`` (``d`` at least ``CURVE_REACTION`` s of travel), from :data:`CURVE_LOOKAHEAD` s ahead
    down to the EV; ``inf`` where no curve limits it. ``kappa``: the heading's change over :data:`CURVE_WINDOW` m.
    ``ValueError`` unless ``lateral_accel`` > 0."""
    if not lateral_accel > 0:
        raise ValueError(f"a curve speed needs a lateral acceleration > 0 m/s^2, got {lateral_accel}")
    ahead = np.arange(0.0, max(speed * CURVE_LOOKAHEAD, 20.0), 1.0)
    half = CURVE_WINDOW / 2
    kappa = np.abs(route.heading_at(s + ahead + half) - route.heading_at(s + ahead - half)) / CURVE_WINDOW
    v_curve2 = lateral_accel / np.maximum(kappa, 1e-9)
    limited = v_curve2 < speed ** 2 + 2 * 10.0 * ahead  # the rest would allow 10 m/s^2 or more: they limit nothing
    if not limited.any():
        return float("inf")
    distance = np.maximum(ahead[limited], max(speed * CURVE_REACTION, 1.0))
    return float(np.min((v_curve2[limited] - speed ** 2) / (2 * distance)))
