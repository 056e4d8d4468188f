"""``cut-in`` (issue 27): dense multi-lane highway; a vehicle in the next lane cuts in ahead of the EV at a short time
gap and then brakes.

A straight road of ``lanes_count`` (default 3) lanes of 4 m, speed limit 30 m/s (highway-env's highway-v0 road). At
every ``reset(seed=...)``, from the env's own ``np_random``:

- the EV's lane, uniform among the lanes, and its speed (``ev_speed``), starting at x = 200 m on the lane's centre;
- the cutter's lane: one of the lanes beside the EV's, uniform among those the road has; its start
  ``cutter_start`` ahead of the EV, centre to centre (negative: behind); the moment its lane change starts
  (``cut_time``, rounded up to the 0.1 s policy step); the time gap at that moment (``time_gap``: the footprint
  gap, bumper to bumper, to an EV that has held its speed, over that speed); then, once it is in the EV's lane,
  its braking: ``cutter_decel`` for ``brake_duration`` (rounded up to the step), or until it stands;
- traffic as in ``stalled-vehicle``: ``density`` vehicles per km per lane from 150 m behind the EV to 400 m
  ahead (centre gaps of 1000 / density m times a uniform factor in [0.7, 1.3], at least 15 m), each at its own
  speed from ``traffic_speed``, each highway-env's ``AggressiveVehicle`` with probability ``aggressive_share``,
  ``DefensiveVehicle`` with probability ``defensive_share``, else an ``IDMVehicle`` (its IDM exponent randomized
  as highway-v0 does); the shares drawn once per episode. The EV's lane holds traffic behind the EV, and ahead
  only beyond where the scripted cutter could reach it (:func:`lead_clearance`); the cutter's lane none from 15 m
  behind the cutter to where it could reach before it leaves the lane (:func:`cutter_lane_clearance`).

The cutter is scripted, not driven by IDM/MOBIL, so that its motion is a function of its draws alone, whatever the
EV does (:class:`CutInVehicle`): it holds ``cutter_speed`` (the speed that puts it ``time_gap`` ahead of an EV
holding ``ev_speed`` at ``cut_time``: ``ev_speed + (L + time_gap x ev_speed - cutter_start) / cut_time``, L the 5 m
length); from ``cut_time`` it crosses to the EV's lane's centre in :data:`LANE_CHANGE` (2 s) on a half-cosine
lateral profile while its progress along the road stays ``speed x dt`` per step; from the end of the lane change it
brakes at ``cutter_decel`` for the duration, clamped at 0; from then on it is an IDM follower in the EV's lane at its
own speed that never accelerates (it brakes only for a vehicle ahead) and never changes lanes. Other traffic is
highway-env's IDM/MOBIL kinds.

Ranges per ``difficulty`` (:data:`DIFFICULTIES`; units as :class:`CutInRanges` says; ``traffic_speed`` 20 - 28
m/s throughout):

==========  ========  ============  ========  ==========  ============  ==============  =======  ==========  =========
difficulty  ev_speed  cutter_start  cut_time  time_gap    cutter_decel  brake_duration  density  aggressive  defensive
==========  ========  ============  ========  ==========  ============  ==============  =======  ==========  =========
easy        20 - 25   0 - 15        3 - 5     1.0 - 1.5   2 - 4         1 - 2           5 - 10   0 - 0.1     0.2 - 0.5
medium      22 - 28   0 - 20        3 - 5     0.6 - 1.0   3 - 6         1 - 3           10 - 16  0.1 - 0.3   0.1 - 0.3
hard        25 - 30   5 - 25        3 - 5     0.3 - 0.6   5 - 8         2 - 6           14 - 20  0.3 - 0.5   0 - 0.2
extreme     25 - 30   5 - 25        3 - 5     0.2 - 0.25  7.5 - 8       6 - 10          14 - 20  0.3 - 0.5   0 - 0.2
==========  ========  ============  ========  ==========  ============  ==============  =======  ==========  =========

``extreme`` came after the suite's leaderboard had saturated ``hard`` (its best policy met 0.99 of the seeds): hard's
road, EV and traffic, with the cutter at the edge of its envelope (the shortest time gap, the hardest braking, to a
stop: 6 s at 7.5 m/s^2 stops any cutter the ranges draw), at the edge of the oracle's cover too (1.6 m at the worst
corner, against hard's 4.9). ``hard`` keeps its ranges, so that its recorded results stay what they were.

The densities stop at 20: above it highway-env's IDM traffic at 20 - 28 m/s jams (to 8 - 16 m/s on the development
seeds), so that the cutter met it in its way on a quarter of the hard episodes. Where traffic does come into its way
so near that keeping :data:`GUARD_GAP` would need more than :data:`GUARD_ONSET`, the cutter brakes for it (up to
:data:`GUARD_MAX`) rather than crash, counted in ``guarded_steps``: the one way it leaves its script.

Every instance leaves a safe plan inside the planning bounds (:func:`least_gap`): the EV holds its speed (input 0)
until the cutter's lane change starts (it is in the observation: the cutter's heading and lateral position), then
brakes at the bounds (:func:`bimp.envs.oracle.brake_at_the_bounds`: -1 m/s^2 more per step down to -7 m/s^2, to a
stop), and keeps at least ``d_min`` (1 m) between its footprint and the cutter's, counted from the start of the
lane change as if the cutter were already in the EV's lane. :class:`CutInRanges` refuses ranges whose worst corner
(of all 64) the plan does not keep ``d_min`` clear, or whose cutter speed leaves [5, 40] m/s. The oracle assumes
that the cutter keeps its script (no guard, no crash) and that traffic that changes into the EV's lane behind the
cutter (MOBIL does, once the EV has slowed) keeps ``d_min`` from the EV: the tests check both on env episodes driven
by the oracle's plan, and that the env's gap to the cutter is the oracle's.

Success: the time limit (15 s) reached without collision or leaving the road; there is no goal.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from types import MappingProxyType

import numpy as np
from highway_env.envs.highway_env import HighwayEnv
from highway_env.vehicle.behavior import IDMVehicle

from bimp.configs import ConfigError, check_fields
from bimp.envs.oracle import brake_at_the_bounds
from bimp.envs.scene import DT, VEHICLE_LENGTH, Bounds
from bimp.envs.suite.family import (
    EV_X,
    MIN_TRAFFIC_GAP,
    Envelope,
    HighwayFamily,
    check_ranges,
    check_shares,
)

TRAFFIC_BEHIND, TRAFFIC_AHEAD = 150.0, 400.0  # m: traffic from this far behind the EV to this far ahead of it
CLEARANCE_MARGIN = 40.0  # m: what the clear stretches ahead keep beyond the cutter's reach at the slowest traffic
LANE_CHANGE = 2.0  # s: the cutter's lane change, start to the EV's lane centre (a peak lateral speed of 3.1 m/s)
CUTTER_SPEED = (5.0, 40.0)  # m/s: the derived cutter speed's range (40: highway-env's Vehicle.MAX_SPEED)
CUTTER_COLOUR = (20, 20, 20)  # near black, as the suite's other scripted vehicle (the stalled one)
GUARD_GAP = 2.0  # m: the footprint gap the scripted cutter keeps to traffic that comes into its way
GUARD_ONSET = 4.0  # m/s^2: it brakes for them only once holding 2 m would need this much, as a late driver
GUARD_MAX = 8.0  # m/s^2: and then at most this hard (the envelope's hardest cutter_decel)
BOUNDS = Bounds()
_EPS = 1e-9


def on_the_step(t):
    """``t`` [s] rounded up to the policy step (0.1 s): when the cutter's scripted events happen. Arrays too."""
    return np.ceil(np.asarray(t, float) / DT - _EPS) * DT


def cutter_speed(ev_speed, cutter_start, cut_time, time_gap):
    """The cutter's speed [m/s] before its braking: the one that brings it from ``cutter_start`` [m, centre ahead of
    the EV's] to ``time_gap`` [s] ahead of an EV holding ``ev_speed`` [m/s] at ``cut_time`` [s] (on the step)."""
    ev_speed = np.asarray(ev_speed, float)
    return ev_speed + (VEHICLE_LENGTH + time_gap * ev_speed - np.asarray(cutter_start, float)) / on_the_step(cut_time)


def least_gap(ev_speed, cutter_start, cut_time, time_gap, cutter_decel, brake_duration,
              bounds: Bounds = BOUNDS) -> np.ndarray:
    """The oracle's least footprint gap [m] to the cutter, from the start of its lane change on (module docstring):
    the EV at ``ev_speed`` brakes at ``bounds`` from the lane change's first step; the cutter, its centre
    ``L + time_gap x ev_speed`` ahead at ``cutter_speed``, brakes at ``cutter_decel`` [m/s^2] for ``brake_duration``
    [s] from :data:`LANE_CHANGE` on. The onset is half a step early so that float clocks meet it on the step."""
    ev_speed, time_gap = np.asarray(ev_speed, float), np.asarray(time_gap, float)
    return brake_at_the_bounds(ev_speed, VEHICLE_LENGTH + time_gap * ev_speed,
                               cutter_speed(ev_speed, cutter_start, cut_time, time_gap), LANE_CHANGE - DT / 2,
                               cutter_decel, react=False, bounds=bounds, duration=on_the_step(brake_duration))


def lead_clearance(cutter_start: float, speed: float, cut_time: float, brake_duration: float,
                   slowest: float) -> float:
    """How far ahead of the EV [m] its lane stays empty at reset: the cutter's position at the end of its script
    (holding ``speed`` that long: an upper bound) less what traffic at ``slowest`` [m/s] covers meanwhile, plus
    :data:`CLEARANCE_MARGIN`; at least ``cutter_start`` plus that margin."""
    script = on_the_step(cut_time) + LANE_CHANGE + on_the_step(brake_duration)
    return float(max(cutter_start, 0.0) + max(speed - slowest, 0.0) * script + CLEARANCE_MARGIN)


def cutter_lane_clearance(speed: float, cut_time: float, slowest: float) -> float:
    """How far ahead of the cutter [m] its own lane stays empty at reset: what it gains on traffic at ``slowest``
    [m/s] until its lane change ends, plus :data:`CLEARANCE_MARGIN`."""
    return float(max(speed - slowest, 0.0) * (on_the_step(cut_time) + LANE_CHANGE) + CLEARANCE_MARGIN)


# Where each range may lie, whatever the difficulty: what the oracle, the road and the episode cover.
ENVELOPE = MappingProxyType({
    "ev_speed": Envelope(15.0, 30.0, "m/s", "the lanes' speed limit is 30 m/s; below 15 it is no longer a highway"),
    "cutter_start": Envelope(-20.0, 40.0, "m", "centre to centre: beside the EV, slightly behind to ahead"),
    "cut_time": Envelope(1.0, 8.0, "s", "the cut starts within the 15 s episode's first 8 s, time left to brake"),
    "time_gap": Envelope(0.2, 3.0, "s", "bumper to bumper; beyond 3 s a lane change is no cut-in"),
    "cutter_decel": Envelope(0.0, 8.0, "m/s^2", "a car's hard braking on a dry road"),
    "brake_duration": Envelope(0.0, 10.0, "s", "rounded up to the 0.1 s step; long enough is braking to a stop"),
    "density": Envelope(0.0, 20.0, "vehicles/km/lane", "above 20 traffic jams ahead of the cutter and its guard "
                        "leaves the oracle's script on about a quarter of hard episodes"),
    "traffic_speed": Envelope(15.0, 30.0, "m/s", "the lanes' speed limit is 30 m/s"),
    "aggressive_share": Envelope(0.0, 1.0, "", "a probability"),
    "defensive_share": Envelope(0.0, 1.0, "", "a probability"),
})
_ORACLE_KEYS = ("ev_speed", "cutter_start", "cut_time", "time_gap", "cutter_decel", "brake_duration")


@dataclasses.dataclass(frozen=True)
class CutInRanges:
    """The family's randomized ranges, each ``(lo, hi)`` drawn uniformly at every reset: ``ev_speed`` [m/s],
    ``cutter_start`` [m, the cutter's centre ahead of the EV's at reset, negative behind], ``cut_time`` [s, when its
    lane change starts], ``time_gap`` [s, bumper to bumper over the EV's speed, at ``cut_time``], ``cutter_decel``
    [m/s^2, a magnitude], ``brake_duration`` [s], ``density`` [vehicles per km per lane], ``traffic_speed`` [m/s,
    each traffic vehicle's], ``aggressive_share`` and ``defensive_share`` [probability of each traffic vehicle's
    kind]. Each inside :data:`ENVELOPE`; the two shares' highs sum to at most 1; the derived cutter speed
    (:func:`cutter_speed`) within :data:`CUTTER_SPEED` on every corner; and the oracle (:func:`least_gap`) at least
    ``d_min`` on every corner of the six ranges it reads. ``ConfigError`` naming the range otherwise."""

    ev_speed: tuple[float, float]
    cutter_start: tuple[float, float]
    cut_time: tuple[float, float]
    time_gap: tuple[float, float]
    cutter_decel: tuple[float, float]
    brake_duration: tuple[float, float]
    density: tuple[float, float]
    traffic_speed: tuple[float, float]
    aggressive_share: tuple[float, float]
    defensive_share: tuple[float, float]

    def __post_init__(self) -> None:
        check_fields(self)
        check_ranges(self, ENVELOPE)
        check_shares(self)
        corners = self.corners()
        speeds = cutter_speed(*(corners[k] for k in ("ev_speed", "cutter_start", "cut_time", "time_gap")))
        if not CUTTER_SPEED[0] <= speeds.min() <= speeds.max() <= CUTTER_SPEED[1]:
            raise ConfigError("cut_time", f"a range that keeps the cutter's speed within {CUTTER_SPEED} m/s with "
                              f"these ev_speed, cutter_start and time_gap", self.cut_time,
                              f"the cutter needs {speeds.min():.1f} - {speeds.max():.1f} m/s to be time_gap ahead "
                              f"at cut_time (ev_speed {self.ev_speed}, cutter_start {self.cutter_start}, "
                              f"time_gap {self.time_gap}): change any of the four")
        gaps = least_gap(**corners)
        worst = int(np.argmin(gaps))
        if gaps[worst] < BOUNDS.d_min:
            # Named time_gap (the knob that always helps), with the worst corner's every value: the range the
            # user changed may be another of the six.
            corner = ", ".join(f"{k} {corners[k][worst]:g}" for k in _ORACLE_KEYS)
            raise ConfigError("time_gap", f"a range whose low leaves the oracle's stop {BOUNDS.d_min:g} m clear "
                              f"with these ranges", self.time_gap,
                              f"outside the oracle's cover: braking at the planning bounds from the cut's start "
                              f"comes within {gaps[worst]:.2f} m of the cutter at the worst corner ({corner}), "
                              f"d_min is {BOUNDS.d_min:g} m; raise time_gap or narrow the others")

    def corners(self) -> dict[str, np.ndarray]:
        """The 64 corners of the six ranges the oracle reads, one array per key."""
        values = np.array(list(itertools.product(*(getattr(self, k) for k in _ORACLE_KEYS))), float)
        return {k: values[:, i] for i, k in enumerate(_ORACLE_KEYS)}

    def least_gap(self) -> float:
        """The oracle's least footprint gap [m] over the corners of the ranges (:func:`least_gap`)."""
        return float(least_gap(**self.corners()).min())


_HARD = CutInRanges(ev_speed=(25.0, 30.0), cutter_start=(5.0, 25.0), cut_time=(3.0, 5.0), time_gap=(0.3, 0.6),
                    cutter_decel=(5.0, 8.0), brake_duration=(2.0, 6.0), density=(14.0, 20.0),
                    traffic_speed=(20.0, 28.0), aggressive_share=(0.3, 0.5), defensive_share=(0.0, 0.2))
DIFFICULTIES = MappingProxyType({
    "easy": CutInRanges(ev_speed=(20.0, 25.0), cutter_start=(0.0, 15.0), cut_time=(3.0, 5.0), time_gap=(1.0, 1.5),
                        cutter_decel=(2.0, 4.0), brake_duration=(1.0, 2.0), density=(5.0, 10.0),
                        traffic_speed=(20.0, 28.0), aggressive_share=(0.0, 0.1), defensive_share=(0.2, 0.5)),
    "medium": CutInRanges(ev_speed=(22.0, 28.0), cutter_start=(0.0, 20.0), cut_time=(3.0, 5.0),
                          time_gap=(0.6, 1.0), cutter_decel=(3.0, 6.0), brake_duration=(1.0, 3.0),
                          density=(10.0, 16.0), traffic_speed=(20.0, 28.0), aggressive_share=(0.1, 0.3),
                          defensive_share=(0.1, 0.3)),
    "hard": _HARD,
    # hard's road, EV and traffic; the cutter at its envelope's edge (module docstring)
    "extreme": dataclasses.replace(_HARD, time_gap=(0.2, 0.25), cutter_decel=(7.5, 8.0), brake_duration=(6.0, 10.0)),
})


class CutInVehicle(IDMVehicle):
    """The scripted cutter (module docstring): its motion is a function of its arguments alone until its braking
    ends, then an IDM follower that never accelerates. ``cut_time``, ``brake_start``, ``brake_duration`` [s from
    reset, on the policy step]; ``target_lane_index``: the EV's lane; ``decel`` [m/s^2]; ``frequency`` [Hz]: the
    simulation's. Its steps are counted, so that the events fall on the same step whatever float error a clock
    would gather."""

    def __init__(self, road, position, heading: float, speed: float, *, target_lane_index, cut_time: float,
                 decel: float, brake_duration: float, frequency: float) -> None:
        super().__init__(road, position, heading, speed, target_speed=speed, enable_lane_change=False)
        self.color = CUTTER_COLOUR
        self.cut_lane_index = target_lane_index
        self.cut_time, self.decel, self.brake_duration = cut_time, decel, brake_duration
        self.brake_start = cut_time + LANE_CHANGE
        self.y0, self.target_y = float(position[1]), float(road.network.get_lane(target_lane_index).position(0, 0)[1])
        self.dt = 1.0 / frequency  # s: one simulation step
        self.steps = 0  # simulation steps taken since reset
        self.guarded_steps = 0  # steps on which it braked for traffic harder than its script (GUARD)

    @classmethod
    def create_from(cls, vehicle: IDMVehicle) -> IDMVehicle:
        """A plain IDM snapshot, for highway-env's trajectory history (``show_trajectories``): highway-env's own
        ``create_from`` builds this class from IDM's arguments, which it does not take (a raw ``TypeError``)."""
        return IDMVehicle.create_from(vehicle)

    def _lateral(self, t: float) -> float:
        """The scripted lateral position [m] at ``t`` [s]: the half-cosine from the own lane's centre to the EV's."""
        s = min(max((t - self.cut_time) / LANE_CHANGE, 0.0), 1.0)
        return self.y0 + (self.target_y - self.y0) * (1.0 - math.cos(math.pi * s)) / 2.0

    def _scripted(self, t: float) -> bool:
        return t < self.brake_start + self.brake_duration - _EPS

    def act(self, action=None) -> None:
        if self.crashed:
            return
        t = self.steps * self.dt
        if self._scripted(t):
            braking = t >= self.brake_start - _EPS and self.speed > 0.0
            scripted = -self.decel if braking else 0.0
            need = self._needed_braking()
            if need > max(-scripted, GUARD_ONSET):
                # Traffic has come into its way (a MOBIL lane change, a jam ahead) nearer than its script can stop
                # for: it brakes as hard as that needs, up to GUARD_MAX, rather than run into it (a crashed vehicle
                # in highway-env stops at its speed per second, harder than any script); counted, since this
                # leaves the oracle's script.
                self.guarded_steps += 1
                scripted = -min(need, GUARD_MAX)
            self.action = {"steering": 0.0, "acceleration": scripted}
            return
        # After its braking: IDM behind whatever is ahead in the EV's lane, never faster than it is.
        front, rear = self.road.neighbour_vehicles(self, self.lane_index)
        self.target_speed = min(self.target_speed, self.speed)
        self.action = {"steering": float(self.steering_control(self.lane_index)),
                       "acceleration": min(0.0, float(self.acceleration(self, front, rear)))}

    def _needed_braking(self) -> float:
        """The constant deceleration [m/s^2] that would keep :data:`GUARD_GAP` to the nearest vehicle ahead in the
        lanes it is in or going to, that vehicle holding its speed; 0 where nothing ahead closes in."""
        need = 0.0
        for lane_index in {self.lane_index, self.target_lane_index}:
            front, _ = self.road.neighbour_vehicles(self, lane_index)
            if front is None:
                continue
            closing = self.speed - front.speed
            gap = self.lane_distance_to(front) - (self.LENGTH + front.LENGTH) / 2 - GUARD_GAP
            if closing > 0.0:
                need = max(need, closing ** 2 / (2.0 * max(gap, 0.1)))
        return need

    def step(self, dt: float) -> None:
        t = self.steps * dt
        self.steps += 1
        if self.crashed or not self._scripted(t):
            super().step(dt)
            return
        if t >= self.cut_time - _EPS:
            self.target_lane_index = self.cut_lane_index  # MOBIL traffic sees where it goes
        # The oracle's kinematics along the road (bimp.envs.oracle): position by the step's starting speed, then the
        # speed, clamped at 0; sideways the scripted profile, the heading along the resulting path.
        dy = self._lateral(t + dt) - self._lateral(t)
        self.position = np.array([self.position[0] + self.speed * dt, self.position[1] + dy])
        self.heading = math.atan2(dy, self.speed * dt) if self.speed > 0.0 else 0.0
        self.speed = max(self.speed + self.action["acceleration"] * dt, 0.0)
        self.timer += dt
        self.on_state_update()


class CutInEnv(HighwayFamily, HighwayEnv):
    """The ``cut-in`` family (module docstring): highway-env's ``HighwayEnv`` road with the family's own population.
    ``self.cutter``: this episode's scripted :class:`CutInVehicle`. Config: highway-env's keys but those its
    population replaces (:attr:`REMOVED_KEYS`), ``lanes_count`` an int in [2, 5], ``difficulty`` and the ranges of
    :class:`CutInRanges`."""

    NAME = "cut-in"
    ID = "cut-in-v0"
    DURATION = 15.0  # s: the latest cut (5 s) and its lane change and braking (up to 6 s) end by 13 s
    TARGET_SPEED = 30.0  # m/s: the lanes' speed limit, as highway-v0's profile
    RANGES = CutInRanges
    DIFFICULTIES = DIFFICULTIES
    LANES_WHY = "a lane beside the EV's to cut in from"

    cutter: CutInVehicle

    def _create_vehicles(self) -> None:
        """The EV, the cutter and the traffic (module docstring), in that order of draws."""
        road, network = self.road, self.road.network
        lanes = network.graph["0"]["1"]
        ev_lane = int(self.np_random.integers(len(lanes)))
        beside = [k for k in (ev_lane - 1, ev_lane + 1) if 0 <= k < len(lanes)]
        cutter_lane = beside[int(self.np_random.integers(len(beside)))]
        self.drawn_params.update(ev_lane=ev_lane, cutter_lane=cutter_lane)
        ev_speed = self._draw("ev_speed")
        start, cut_time, time_gap = self._draw("cutter_start"), self._draw("cut_time"), self._draw("time_gap")
        decel, brake_duration = self._draw("cutter_decel"), self._draw("brake_duration")
        density = self._draw("density")
        aggressive, defensive = self._draw("aggressive_share"), self._draw("defensive_share")
        speed = float(cutter_speed(ev_speed, start, cut_time, time_gap))
        self.drawn_params["cutter_speed"] = speed

        lane, side = lanes[ev_lane], lanes[cutter_lane]
        self._add_ev(lane, ev_speed)
        self.cutter = CutInVehicle(road, side.position(EV_X + start, 0.0), side.heading_at(EV_X + start), speed,
                                   target_lane_index=("0", "1", ev_lane), cut_time=float(on_the_step(cut_time)),
                                   decel=decel, brake_duration=float(on_the_step(brake_duration)),
                                   frequency=float(self.config["simulation_frequency"]))
        road.vehicles.append(self.cutter)

        slowest = self.config["traffic_speed"][0]
        keep_out = {  # per lane: the stretches [from, to) of x where no traffic starts (module docstring)
            ev_lane: [(EV_X - MIN_TRAFFIC_GAP, EV_X + lead_clearance(start, speed, cut_time, brake_duration,
                                                                     slowest))],
            cutter_lane: [(EV_X + start - MIN_TRAFFIC_GAP,
                           EV_X + start + cutter_lane_clearance(speed, cut_time, slowest))],
        }
        self._place_traffic(lanes, EV_X - TRAFFIC_BEHIND, EV_X + TRAFFIC_AHEAD, density, aggressive, defensive,
                            keep_out=keep_out)


