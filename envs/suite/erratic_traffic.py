"""``erratic-traffic`` (issue 27): traffic whose braking and lane changes carry heavy-tailed noise (hard brakes of
Student's-t magnitude), the world the paper's heavy-tailed planners are meant for.

A straight road of ``lanes_count`` (default 3) lanes of 4 m, speed limit 30 m/s (highway-env's highway-v0 road), with
traffic in every lane, the EV's included. At every ``reset(seed=...)``, from the env's own ``np_random``:

- the EV's lane, uniform among the lanes, and its speed (``ev_speed``), starting at x = 200 m on the lane's centre;
- its leader: an :class:`ErraticVehicle` ``leader_gap`` ahead in the EV's lane (centre to centre) at a speed drawn
  from ``traffic_speed`` (recorded as ``leader_speed``);
- the episode's noise, shared by every traffic vehicle: ``brake_rate`` (hard brakes per vehicle per second),
  ``brake_scale`` and ``nu`` (a brake's magnitude is ``brake_scale x |t_nu|``, Student's t with ``nu`` degrees of
  freedom: the smaller ``nu``, the heavier the tail, capped at :data:`BRAKE_CAP`), ``brake_duration`` (each brake
  is held for a time uniform in [0.5, 1.5] x it) and ``lane_noise`` (the scale of MOBIL's noise, below);
- traffic in every lane as in ``stalled-vehicle``, from 100 m behind the EV to 300 m ahead of it: ``density``
  vehicles per km per lane (centre gaps of 1000 / density m times a uniform factor in [0.7, 1.3], at least 15 m),
  each an :class:`ErraticVehicle` at its own speed from ``traffic_speed`` (its IDM target), its IDM exponent
  randomized as highway-v0 randomizes it. In the EV's lane none starts within 15 m behind the EV or between the
  EV and 15 m past the leader.

Every traffic vehicle is an :class:`ErraticVehicle`: highway-env's ``IDMVehicle`` (IDM car following, MOBIL lane
changes) with two kinds of heavy-tailed events, every draw from the env's ``np_random`` (the vehicles hold it; none
from numpy's global generator):

- **hard brakes**: a Poisson process of ``brake_rate`` per second; each brake pulls the IDM acceleration down to
  ``-min(brake_scale x |t_nu|, 8)`` m/s^2 for its hold time, then IDM takes over again (the next brake comes an
  exponential time after this one ends). :data:`BRAKE_CAP` (8 m/s^2, about 0.8 g) is what a car's tyres give on a
  dry road: the t's tail is unbounded, a car's braking is not. IDM's own braking reaches the same cap (highway-env
  clips it at 6 m/s^2), so that a follower can answer a hard brake ahead as hard as it was made; and a vehicle
  stops at 0, it never reverses (highway-env's IDM backs up when it stands too near);
- **erratic lane changes**: at each of MOBIL's evaluations of a lane beside (every second, once per side lane) one
  draw ``e ~ t_nu``, and MOBIL decides with its gain threshold lowered and the braking it may impose on its new
  follower raised by ``lane_noise x |e|``
  (highway-env's 0.2 and 2 m/s^2): mostly MOBIL, sometimes a lane change for no gain into a short gap. Whatever the
  noise, a lane change is made only into a gap that the **safety bound** (:func:`gap_is_safe`) allows: its new
  follower, braking at the planning bounds from its own current input (the EV's last one, a traffic vehicle's IDM
  command, clipped to [-7, 3] m/s^2; -1 m/s^2 more per step to -7), keeps ``d_min`` (1 m) behind it even if it
  brakes at the cap to a stop at once; and it itself, braking at the cap at once, keeps ``d_min`` behind its new
  leader braking the same. The first keeps every instance solvable for an EV cut in on (below); the second keeps the
  changer off its new leader's bumper.

Ranges per ``difficulty`` (:data:`DIFFICULTIES`; units as :class:`ErraticTrafficRanges` says; ``traffic_speed``
20 - 28 m/s throughout):

==========  ========  ==========  =======  ===========  ===========  ==============  =========  ==========
difficulty  ev_speed  leader_gap  density  brake_rate   brake_scale  brake_duration  nu         lane_noise
==========  ========  ==========  =======  ===========  ===========  ==============  =========  ==========
easy        20 - 25   60 - 100    5 - 10   0.01 - 0.03  0.5 - 1.5    0.5 - 1.5       4 - 6      0 - 0.2
medium      22 - 28   50 - 80     10 - 16  0.03 - 0.06  1 - 2.5      1 - 2           2.5 - 4    0.1 - 0.5
hard        25 - 30   56 - 70     16 - 20  0.15 - 0.3   3 - 6        1.5 - 3         1.2 - 2    2 - 4
extreme     25 - 30   56 - 70     18 - 20  0.3 - 0.5    5 - 8        2 - 4           1 - 1.5    3 - 5
==========  ========  ==========  =======  ===========  ===========  ==============  =========  ==========

``extreme`` came after the suite's leaderboard had saturated ``hard`` (its best policy met 0.96 of the seeds): the same
road, EV and leader as ``hard`` (so the same oracle corner), with the noise at the top of its envelope (``brake_rate``
1.8 times hard's, about 40% of brakes at the cap against 25%, held longer, Cauchy-like tails, nearly any safe gap
taken). ``hard`` keeps its ranges, so that its recorded results stay what they were.

Every instance leaves a safe plan inside the planning bounds (:func:`least_gap`): the EV brakes at the bounds from its
first step (:func:`bimp.envs.oracle.brake_at_the_bounds`: -1 m/s^2 more per step down to -7 m/s^2, to a stop) and
keeps at least ``d_min`` to its leader under the worst the family allows, the leader braking at the cap (8 m/s^2) to
a stop at once. That worst case bounds every vehicle ahead in the EV's lane: each starts at least as far and as fast
as the worst corner (``leader_gap`` low, ``traffic_speed`` low) and none brakes harder than the cap; one that
changes into the EV's lane ahead of it does so only where the safety bound holds toward the EV (or, beyond the
leader, toward a vehicle the EV already keeps clear of), which is the same oracle from the EV's input at that moment
(the braking EV's is at most 0). :class:`ErraticTrafficRanges` refuses ranges whose worst corner (``ev_speed``
high, ``leader_gap`` low, ``traffic_speed`` low) the plan does not keep ``d_min`` clear, naming ``leader_gap``.
What the oracle does not cover: collisions among the traffic ahead (a crashed highway-env vehicle stops harder than
the cap and is pushed back by the impact), and traffic that rear-ends the braking or standing EV (not the EV's fault,
but success counts every collision); the tests count both on env episodes driven by the oracle's plan.

Success: the time limit (20 s) reached without collision or leaving the road; there is no goal.
"""

from __future__ import annotations

import dataclasses
import math
from types import MappingProxyType

import numpy as np
from highway_env.envs.highway_env import HighwayEnv
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.kinematics import Vehicle

from bimp.configs import check_fields
from bimp.envs.oracle import brake_at_the_bounds
from bimp.envs.scene import Bounds
from bimp.envs.suite.family import EV_X, MIN_TRAFFIC_GAP, Envelope, HighwayFamily, check_leader_gap, check_ranges

TRAFFIC_BEHIND, TRAFFIC_AHEAD = 100.0, 300.0  # m: traffic from this far behind the EV to this far ahead of it
BRAKE_CAP = 8.0  # m/s^2: the hardest braking of any traffic vehicle, a car's tyres on a dry road (about 0.8 g)
HOLD = (0.5, 1.5)  # each brake's hold time: brake_duration times a factor uniform in this range
BOUNDS = Bounds()
# How a traffic vehicle that changes lanes may brake for its new leader in the safety bound: at the cap at once.
TRAFFIC_BRAKING = Bounds(accel=(-BRAKE_CAP, BOUNDS.accel[1]), accel_rate=2.0 * BRAKE_CAP)
_EPS = 1e-9


def least_gap(ev_speed, leader_gap, leader_speed, bounds: Bounds = BOUNDS) -> np.ndarray:
    """The oracle's least footprint gap [m] to the leader: the EV at ``ev_speed`` [m/s] brakes at ``bounds`` from its
    first step (input 0 before), the leader ``leader_gap`` [m] ahead (centre to centre) at ``leader_speed`` [m/s]
    brakes at :data:`BRAKE_CAP` to a stop at once. Arrays broadcast."""
    return brake_at_the_bounds(ev_speed, leader_gap, leader_speed, 0.0, BRAKE_CAP, react=False, bounds=bounds)


def gap_is_safe(follower_speed: float, gap: float, leader_speed: float, a0: float = BOUNDS.accel[1],
                bounds: Bounds = BOUNDS) -> bool:
    """The safety bound of an erratic lane change: whether a follower at ``follower_speed`` [m/s], its input ``a0``
    [m/s^2], braking at ``bounds`` from now keeps ``d_min`` behind a leader ``gap`` [m] ahead (centre to centre) at
    ``leader_speed`` [m/s] that brakes at :data:`BRAKE_CAP` to a stop at once."""
    if gap - 5.0 < bounds.d_min:  # already nearer than d_min (the footprints' 5 m length)
        return False
    return bool(brake_at_the_bounds(follower_speed, gap, leader_speed, 0.0, BRAKE_CAP, react=False, bounds=bounds,
                                    a0=a0) >= bounds.d_min)


class ErraticVehicle(IDMVehicle):
    """highway-env's IDM/MOBIL vehicle with heavy-tailed hard brakes and lane changes (module docstring).

    ``rng``: the env's ``np_random`` (every draw comes from it); ``brake_rate`` [1/s], ``brake_scale`` [m/s^2],
    ``brake_duration`` [s], ``nu`` [degrees of freedom], ``lane_noise`` [m/s^2]: the episode's noise; ``frequency``
    [Hz]: the simulation's. Logged: ``brakes`` (each brake's start [s from reset], magnitude [m/s^2] and hold [s]),
    ``erratic_lane_changes`` (lane changes the noise-free MOBIL would not have made), ``refused_lane_changes``
    (those MOBIL wanted and the safety bound refused)."""

    ACC_MAX = BRAKE_CAP  # IDM's braking up to the cap; its accelerating stays under COMFORT_ACC_MAX (3 m/s^2)

    def __init__(self, road, position, heading: float, speed: float, *, rng: np.random.Generator,
                 brake_rate: float, brake_scale: float, brake_duration: float, nu: float, lane_noise: float,
                 frequency: float) -> None:
        super().__init__(road, position, heading, speed)
        self.rng = rng
        self.brake_rate, self.brake_scale, self.brake_duration = brake_rate, brake_scale, brake_duration
        self.nu, self.lane_noise = nu, lane_noise
        self.dt = 1.0 / frequency  # s: one simulation step
        self.steps = 0  # simulation steps taken since reset: the clock, without a float sum's drift
        self.brakes: list[tuple[float, float, float]] = []
        self.brake_until, self.brake = -math.inf, 0.0
        self.next_brake = self._wait(0.0)
        self.erratic_lane_changes = self.refused_lane_changes = 0

    @classmethod
    def create_from(cls, vehicle: IDMVehicle) -> IDMVehicle:
        """A plain IDM snapshot, for highway-env's trajectory history (``show_trajectories``): highway-env's own
        ``create_from`` builds this class from IDM's arguments, which it does not take (a raw ``TypeError``)."""
        return IDMVehicle.create_from(vehicle)

    def randomize_behavior(self) -> None:
        self.DELTA = self.rng.uniform(*self.DELTA_RANGE)  # as highway-env's, from the env's generator by name

    def _wait(self, t: float) -> float:
        """When [s] the next brake starts after ``t``: an exponential wait of mean 1 / brake_rate."""
        return t + float(self.rng.exponential(1.0 / self.brake_rate)) if self.brake_rate > 0.0 else math.inf

    def act(self, action=None) -> None:
        if self.crashed:
            return
        super().act()  # IDM and MOBIL (with the noise of self.mobil)
        t = self.steps * self.dt
        if t >= self.next_brake - _EPS:
            self.brake = min(self.brake_scale * abs(float(self.rng.standard_t(self.nu))), BRAKE_CAP)
            hold = self.brake_duration * float(self.rng.uniform(*HOLD))
            self.brakes.append((t, self.brake, hold))
            self.brake_until = t + hold
            self.next_brake = self._wait(self.brake_until)
        a = float(self.action["acceleration"])
        if t < self.brake_until - _EPS:
            a = min(a, -self.brake)
        # At most the cap, and no further than to a stop: a braking vehicle stands, it does not back up.
        self.action["acceleration"] = max(a, -BRAKE_CAP, -self.speed / self.dt)

    def step(self, dt: float) -> None:
        self.steps += 1
        super().step(dt)
        self.speed = max(self.speed, 0.0)  # float error of the last braking step

    def acceleration(self, ego_vehicle, front_vehicle=None, rear_vehicle=None) -> float:
        """highway-env's IDM acceleration [m/s^2] of ``ego_vehicle``; one without an IDM target (the EV, a plain
        kinematic vehicle) judged as a driver that wants its lane's speed limit. highway-env reads a missing target
        as 0 m/s and predicts such a follower braking at about 1e12 m/s^2, so that MOBIL would never change lanes
        ahead of the EV."""
        if isinstance(ego_vehicle, Vehicle) and not hasattr(ego_vehicle, "target_speed"):
            lane = ego_vehicle.lane
            ego_vehicle.target_speed = lane.speed_limit if lane is not None and lane.speed_limit else ego_vehicle.speed
            try:
                return super().acceleration(ego_vehicle, front_vehicle, rear_vehicle)
            finally:
                del ego_vehicle.target_speed
        return super().acceleration(ego_vehicle, front_vehicle, rear_vehicle)

    def mobil(self, lane_index) -> bool:
        """MOBIL with its threshold and imposed-braking limit moved by ``lane_noise x |t_nu|`` (one draw per
        decision), then the safety bound (:func:`gap_is_safe`) toward both new neighbours."""
        impatience = self.lane_noise * abs(float(self.rng.standard_t(self.nu))) if self.lane_noise > 0.0 else 0.0
        self.LANE_CHANGE_MIN_ACC_GAIN = IDMVehicle.LANE_CHANGE_MIN_ACC_GAIN - impatience
        self.LANE_CHANGE_MAX_BRAKING_IMPOSED = IDMVehicle.LANE_CHANGE_MAX_BRAKING_IMPOSED + impatience
        wanted = super().mobil(lane_index)
        if not wanted:
            return False
        leader, follower = self.road.neighbour_vehicles(self, lane_index)
        # The follower's own input (the EV's last one, a traffic vehicle's IDM command), within the bounds: the
        # bound is that the follower has a safe plan from where it is, whatever it was doing.
        a0 = float(np.clip(getattr(follower, "action", {}).get("acceleration", 0.0), *BOUNDS.accel))
        if (follower is not None and not gap_is_safe(follower.speed, follower.lane_distance_to(self), self.speed,
                                                     a0=a0)) \
                or (leader is not None and not gap_is_safe(self.speed, self.lane_distance_to(leader), leader.speed,
                                                           a0=0.0, bounds=TRAFFIC_BRAKING)):
            self.refused_lane_changes += 1
            return False
        if impatience > 0.0:
            del self.LANE_CHANGE_MIN_ACC_GAIN, self.LANE_CHANGE_MAX_BRAKING_IMPOSED  # highway-env's class values
            self.erratic_lane_changes += not super().mobil(lane_index)
        return True


# Where each range may lie, whatever the difficulty: what the oracle, the road and the episode cover.
ENVELOPE = MappingProxyType({
    "ev_speed": Envelope(15.0, 30.0, "m/s", "the lanes' speed limit is 30 m/s; below 15 it is no longer a highway"),
    "leader_gap": Envelope(15.0, 250.0, "m", "centre to centre: IDM's 15 m jam spacing to the road a planner sees"),
    "density": Envelope(0.0, 20.0, "vehicles/km/lane", "above 20 highway-env's IDM traffic at 20 - 28 m/s jams"),
    "traffic_speed": Envelope(15.0, 30.0, "m/s", "the lanes' speed limit is 30 m/s"),
    "brake_rate": Envelope(0.0, 0.5, "1/s", "hard brakes per vehicle per second; 0.5: one every 2 s, on and off"),
    "brake_scale": Envelope(0.0, BRAKE_CAP, "m/s^2", "a brake's magnitude is brake_scale x |t_nu|, capped at 8"),
    "brake_duration": Envelope(0.1, 5.0, "s", "a brake's mean hold; from 0.1 s (one step) to 5 s (a stop from 30 "
                               "m/s at 6 m/s^2)"),
    "nu": Envelope(1.0, 30.0, "", "Student's t degrees of freedom: 1 is Cauchy's tail, above 30 it is Gaussian's"),
    "lane_noise": Envelope(0.0, 5.0, "m/s^2", "the scale of MOBIL's noise; 5 lets nearly any gap the safety bound "
                           "allows be taken"),
})


@dataclasses.dataclass(frozen=True)
class ErraticTrafficRanges:
    """The family's randomized ranges, each ``(lo, hi)`` drawn uniformly at every reset: ``ev_speed`` [m/s],
    ``leader_gap`` [m, the leader's centre ahead of the EV's], ``density`` [vehicles per km per lane],
    ``traffic_speed`` [m/s, each traffic vehicle's, the leader's too], ``brake_rate`` [hard brakes per vehicle per
    second], ``brake_scale`` [m/s^2], ``brake_duration`` [s, a brake's mean hold], ``nu`` [Student's t degrees of
    freedom], ``lane_noise`` [m/s^2]. Each inside :data:`ENVELOPE`; and the oracle (:func:`least_gap`) at least
    ``d_min`` at the worst corner (``ev_speed`` high, ``leader_gap`` low, ``traffic_speed`` low). ``ConfigError``
    naming the range otherwise."""

    ev_speed: tuple[float, float]
    leader_gap: tuple[float, float]
    density: tuple[float, float]
    traffic_speed: tuple[float, float]
    brake_rate: tuple[float, float]
    brake_scale: tuple[float, float]
    brake_duration: tuple[float, float]
    nu: tuple[float, float]
    lane_noise: tuple[float, float]

    def __post_init__(self) -> None:
        check_fields(self)
        check_ranges(self, ENVELOPE)
        check_leader_gap(self, self.least_gap(), BOUNDS.d_min, f"braking at {BRAKE_CAP:g} m/s^2 to a stop at once")

    def least_gap(self) -> float:
        """The oracle's least footprint gap [m] at the ranges' worst corner (the fastest EV, the nearest and slowest
        leader)."""
        return float(least_gap(self.ev_speed[1], self.leader_gap[0], self.traffic_speed[0]))


DIFFICULTIES = MappingProxyType({
    "easy": ErraticTrafficRanges(ev_speed=(20.0, 25.0), leader_gap=(60.0, 100.0), density=(5.0, 10.0),
                                 traffic_speed=(20.0, 28.0), brake_rate=(0.01, 0.03), brake_scale=(0.5, 1.5),
                                 brake_duration=(0.5, 1.5), nu=(4.0, 6.0), lane_noise=(0.0, 0.2)),
    "medium": ErraticTrafficRanges(ev_speed=(22.0, 28.0), leader_gap=(50.0, 80.0), density=(10.0, 16.0),
                                   traffic_speed=(20.0, 28.0), brake_rate=(0.03, 0.06), brake_scale=(1.0, 2.5),
                                   brake_duration=(1.0, 2.0), nu=(2.5, 4.0), lane_noise=(0.1, 0.5)),
    "hard": ErraticTrafficRanges(ev_speed=(25.0, 30.0), leader_gap=(56.0, 70.0), density=(16.0, 20.0),
                                 traffic_speed=(20.0, 28.0), brake_rate=(0.15, 0.3), brake_scale=(3.0, 6.0),
                                 brake_duration=(1.5, 3.0), nu=(1.2, 2.0), lane_noise=(2.0, 4.0)),
    "extreme": ErraticTrafficRanges(ev_speed=(25.0, 30.0), leader_gap=(56.0, 70.0), density=(18.0, 20.0),
                                    traffic_speed=(20.0, 28.0), brake_rate=(0.3, 0.5), brake_scale=(5.0, 8.0),
                                    brake_duration=(2.0, 4.0), nu=(1.0, 1.5), lane_noise=(3.0, 5.0)),
})


class ErraticTrafficEnv(HighwayFamily, HighwayEnv):
    """The ``erratic-traffic`` family (module docstring): highway-env's ``HighwayEnv`` road with the family's own
    population, every traffic vehicle an :class:`ErraticVehicle`. ``self.leader``: the EV's leader at reset.
    Config: highway-env's keys but those its population replaces (:attr:`REMOVED_KEYS`), ``lanes_count`` an int in
    [2, 5], ``difficulty`` and the ranges of :class:`ErraticTrafficRanges`."""

    NAME = "erratic-traffic"
    ID = "erratic-traffic-v0"
    DURATION = 20.0  # s: on hard the leader brakes 1 - 5 times in it (3 on average, seeds 0-31)
    TARGET_SPEED = 30.0  # m/s: the lanes' speed limit, as highway-v0's profile
    RANGES = ErraticTrafficRanges
    DIFFICULTIES = DIFFICULTIES
    LANES_WHY = "a lane beside the EV's for the traffic's lane changes"

    leader: ErraticVehicle

    def _create_vehicles(self) -> None:
        """The EV, its leader and the traffic (module docstring), in that order of draws."""
        lanes = self.road.network.graph["0"]["1"]
        ev_lane = int(self.np_random.integers(len(lanes)))
        self.drawn_params["ev_lane"] = ev_lane
        ev_speed = self._draw("ev_speed")
        gap = self._draw("leader_gap")
        leader_speed = float(self.np_random.uniform(*self.config["traffic_speed"]))
        self.drawn_params["leader_speed"] = leader_speed
        density = self._draw("density")
        self._noise = {key: self._draw(key) for key in ("brake_rate", "brake_scale", "brake_duration", "nu",
                                                         "lane_noise")}

        lane = lanes[ev_lane]
        self._add_ev(lane, ev_speed)
        self.leader = self._erratic(lane, EV_X + gap, leader_speed)
        keep_out = {ev_lane: [(EV_X - MIN_TRAFFIC_GAP, EV_X + gap + MIN_TRAFFIC_GAP)]}
        self._place_traffic(lanes, EV_X - TRAFFIC_BEHIND, EV_X + TRAFFIC_AHEAD, density, 0.0, 0.0, keep_out=keep_out)

    def _erratic(self, lane, x: float, speed: float) -> ErraticVehicle:
        """An :class:`ErraticVehicle` at ``x`` [m along ``lane``] and ``speed`` [m/s, its IDM target], with the
        episode's noise and its IDM exponent randomized; on the road, and returned."""
        vehicle = ErraticVehicle(self.road, lane.position(x, 0.0), lane.heading_at(x), speed, rng=self.np_random,
                                 frequency=float(self.config["simulation_frequency"]), **self._noise)
        vehicle.randomize_behavior()
        self.road.vehicles.append(vehicle)
        return vehicle

    def _traffic_vehicle(self, lane, x: float, aggressive: float, defensive: float,
                         place: bool = True) -> ErraticVehicle | None:
        """One traffic vehicle of ``_place_traffic``: an :class:`ErraticVehicle` (no kind drawn), its speed drawn from
        ``traffic_speed``; placed where ``place``, else None (drawn all the same)."""
        speed = float(self.np_random.uniform(*self.config["traffic_speed"]))
        return self._erratic(lane, x, speed) if place else None
