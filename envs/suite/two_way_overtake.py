"""``two-way-overtake`` (issue 27): pass a slow vehicle on a two-way road, with oncoming gaps some of which are too
short.

highway-env's two-way-v0 road (a lane each way, 4 m, the EV's lane on the right; the lane of the oncoming traffic is
the one to pass in), 2000 m long, every lane's speed limit 25 m/s (a rural road's 90 km/h). At every
``reset(seed=...)``, from the env's own ``np_random``:

- the EV in the right lane at x = 200 m at ``ev_speed``;
- the slow vehicle ``slow_distance`` ahead of it (centre to centre) in the same lane: highway-env's ``IDMVehicle``
  holding ``slow_speed`` (its target), never changing lanes;
- the oncoming stream: highway-env ``IDMVehicle`` s in the other lane driving towards the EV, the first
  ``oncoming_first`` ahead of the EV, each next one an ``oncoming_gap`` further (centre to centre, each gap drawn),
  none beyond ``oncoming_until``; each holds its own speed drawn from ``oncoming_speed``. Past the stream the road is
  clear. highway-env's IDM sees a vehicle in its lane whichever way it drives: an oncoming vehicle brakes for an EV
  in its lane, and hard (highway-env's doing, not the reference's).

Ranges per ``difficulty`` (:data:`DIFFICULTIES`; m/s and m):

==========  ========  ==========  ============  ==============  ==============  ============  ==============
difficulty  ev_speed  slow_speed  slow_distance  oncoming_speed  oncoming_first  oncoming_gap  oncoming_until
==========  ========  ==========  ============  ==============  ==============  ============  ==============
easy        18 - 22   10 - 13     40 - 60       18 - 22         250 - 400       400 - 800     400 - 650
medium      20 - 24   12 - 15     35 - 60       20 - 24         200 - 400       250 - 650     600 - 750
hard        22 - 25   14 - 17     30 - 50       22 - 25         150 - 350       150 - 550     700 - 850
==========  ========  ==========  ============  ==============  ==============  ============  ==============

A pass at hard takes about 8 - 9 s in the oncoming lane (about 45 m to gain on a vehicle 8 - 11 m/s slower,
accelerating at 3 m/s^2, and the lane changes), a gap of about 370 m at the closing speed: some gaps of hard's
150 - 550 m are long enough, most are not.

The behaviour layer (the reference every planner reads, and the ``idm`` policy) is
:class:`bimp.envs.highway.behaviour.OvertakeDriver`: it pulls out on a fixed critical gap of 8 s to the nearest
oncoming vehicle, without checking that the pass fits it, and falls back behind the slow vehicle when the pass no
longer fits (a pull-out not begun is withdrawn). Some gaps it takes are too short.

**Goal** (success needs it, as exit-v0's exit): the slow vehicle passed, the EV back in its lane (its centre within
1 m of the lane's) at least :data:`PASSED` m ahead of the slow vehicle's centre. The episode ends there; the time
limit (40 s) without it is a failure. Waiting behind the slow vehicle is safe and never succeeds.

Every instance leaves a safe plan inside the planning bounds, and a plan that meets the goal:

- **safe**: braking behind the slow vehicle at the bounds from the first step (:func:`bimp.envs.oracle
  .brake_at_the_bounds` with the slow vehicle holding its speed) keeps at least ``d_min`` (1 m) at the ranges'
  worst corner (the fastest EV, the slowest and nearest slow vehicle); ranges that fail are refused naming
  ``slow_distance``. From there the EV follows the slow vehicle, which never brakes (nothing is ahead of it);
- **the goal**: the last oncoming vehicle has met an EV that follows the slow vehicle by (``oncoming_until``'s high
  + 5 m) / (``oncoming_speed``'s low + ``slow_speed``'s low) s, and the road is clear from then; a pass on a clear
  road takes at most :data:`CLEAR_PASS` s. Ranges that leave less than that before the time limit are refused
  naming ``oncoming_until``. The tests drive that plan (the ``idm`` policy clipped to the bounds, pulling out only
  onto a clear road) on whole episodes, seeds 0-99 per difficulty (a slow test): goal reached, no collision, and
  within :data:`CLEAR_PASS` of the road clearing.
"""

from __future__ import annotations

import dataclasses
from types import MappingProxyType

from highway_env.envs.two_way_env import TwoWayEnv
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.kinematics import Vehicle

from bimp.configs import ConfigError, check_fields
from bimp.envs.oracle import NEVER, brake_at_the_bounds
from bimp.envs.scene import VEHICLE_LENGTH, Bounds
from bimp.envs.suite.family import EV_X, Envelope, Family, check_ranges

ROAD_LENGTH = 2000.0  # m: the EV drives at most 40 s x 25 m/s from x = 200 m; the stream starts within 1100 m
SPEED_LIMIT = 25.0  # m/s, every lane
RIGHT, PASSING, ONCOMING = ("a", "b", 1), ("a", "b", 0), ("b", "a", 0)  # two-way-v0's lanes
PASSED = VEHICLE_LENGTH + 5.0  # m, centre to centre: the goal's lead on the slow vehicle
DURATION = 40.0  # s: bimp's profile of two-way-v0 too; the road clears by 25 s at the latest, 15 s before it
CLEAR_PASS = 15.0  # s: a pass on a clear road, from following the slow vehicle to the goal (the slow test shows it)
SLOW_COLOUR = (200, 100, 0)  # orange: the vehicle to pass
BOUNDS = Bounds()

ENVELOPE = MappingProxyType({
    "ev_speed": Envelope(10.0, 25.0, "m/s", "the lanes' speed limit is 25 m/s"),
    "slow_speed": Envelope(5.0, 20.0, "m/s", "at least 5 m/s under the speed limit: a vehicle worth passing"),
    "slow_distance": Envelope(20.0, 150.0, "m", "centre to centre; beyond 150 m there is nothing to pass yet"),
    "oncoming_speed": Envelope(10.0, 25.0, "m/s", "the lanes' speed limit is 25 m/s"),
    "oncoming_first": Envelope(50.0, 1000.0, "m", "ahead of the EV, centre to centre"),
    "oncoming_gap": Envelope(50.0, 1000.0, "m", "centre to centre; under 50 m IDM's gap at 25 m/s"),
    "oncoming_until": Envelope(50.0, 1100.0, "m", "ahead of the EV, inside the 2000 m road"),
})


@dataclasses.dataclass(frozen=True)
class TwoWayOvertakeRanges:
    """The family's randomized ranges, each ``(lo, hi)`` drawn uniformly at every reset (module docstring; m/s and
    m): ``ev_speed``, ``slow_speed``, ``slow_distance`` (the slow vehicle's centre ahead of the EV's),
    ``oncoming_speed`` (each oncoming vehicle's), ``oncoming_first`` (the first oncoming vehicle's centre ahead of the
    EV's), ``oncoming_gap`` (each next one's further), ``oncoming_until`` (none beyond). Each inside
    :data:`ENVELOPE`, and both oracles (module docstring) hold at the worst corner; ``ConfigError`` naming the range
    otherwise."""

    ev_speed: tuple[float, float]
    slow_speed: tuple[float, float]
    slow_distance: tuple[float, float]
    oncoming_speed: tuple[float, float]
    oncoming_first: tuple[float, float]
    oncoming_gap: tuple[float, float]
    oncoming_until: tuple[float, float]

    def __post_init__(self) -> None:
        check_fields(self)
        check_ranges(self, ENVELOPE)
        gap = self.least_gap()
        if gap < BOUNDS.d_min:
            raise ConfigError("slow_distance", f"a range whose low leaves the oracle's braking d_min with ev_speed "
                              f"up to {self.ev_speed[1]:g} m/s and slow_speed from {self.slow_speed[0]:g} m/s",
                              self.slow_distance, f"outside the oracle's cover: braking at the planning bounds "
                              f"from the first step comes {gap:.2f} m from the slow vehicle, d_min is "
                              f"{BOUNDS.d_min:g} m")
        if self.oncoming_first[1] > self.oncoming_until[0]:
            raise ConfigError("oncoming_until", f"a range whose low is at least oncoming_first's high "
                              f"({self.oncoming_first[1]:g} m)", self.oncoming_until,
                              "else a draw may leave the stream empty")
        clear = self.clear_time()
        if clear + CLEAR_PASS > DURATION:
            raise ConfigError("oncoming_until", f"a range whose high clears the road by "
                              f"{DURATION - CLEAR_PASS:g} s", self.oncoming_until,
                              f"outside the oracle's cover: the last oncoming vehicle meets the EV after "
                              f"{clear:.1f} s, and a pass on the clear road takes up to {CLEAR_PASS:g} s of the "
                              f"{DURATION:g} s")

    def least_gap(self) -> float:
        """The safe oracle's least footprint gap [m] to the slow vehicle at the worst corner (module docstring)."""
        return float(brake_at_the_bounds(self.ev_speed[1], self.slow_distance[0], self.slow_speed[0], NEVER, 0.0,
                                         react=False, bounds=BOUNDS))

    def clear_time(self) -> float:
        """The latest time [s] at which the last oncoming vehicle has passed an EV following the slow vehicle."""
        return (self.oncoming_until[1] + VEHICLE_LENGTH) / (self.oncoming_speed[0] + self.slow_speed[0])


DIFFICULTIES = MappingProxyType({
    "easy": TwoWayOvertakeRanges(ev_speed=(18.0, 22.0), slow_speed=(10.0, 13.0), slow_distance=(40.0, 60.0),
                                 oncoming_speed=(18.0, 22.0), oncoming_first=(250.0, 400.0),
                                 oncoming_gap=(400.0, 800.0), oncoming_until=(400.0, 650.0)),
    "medium": TwoWayOvertakeRanges(ev_speed=(20.0, 24.0), slow_speed=(12.0, 15.0), slow_distance=(35.0, 60.0),
                                   oncoming_speed=(20.0, 24.0), oncoming_first=(200.0, 400.0),
                                   oncoming_gap=(250.0, 650.0), oncoming_until=(600.0, 750.0)),
    "hard": TwoWayOvertakeRanges(ev_speed=(22.0, 25.0), slow_speed=(14.0, 17.0), slow_distance=(30.0, 50.0),
                                 oncoming_speed=(22.0, 25.0), oncoming_first=(150.0, 350.0),
                                 oncoming_gap=(150.0, 550.0), oncoming_until=(700.0, 850.0)),
})


class TwoWayOvertakeEnv(Family, TwoWayEnv):
    """The ``two-way-overtake`` family (module docstring): highway-env's ``TwoWayEnv`` road, 2000 m at 25 m/s, with
    the family's own population and a goal. ``self.slow_vehicle``: the vehicle to pass. Config: highway-env's keys
    (``other_vehicles_type`` refused: the family's vehicles are its own), ``difficulty`` and the ranges of
    :class:`TwoWayOvertakeRanges`."""

    NAME = "two-way-overtake"
    ID = "two-way-overtake-v0"
    DURATION = DURATION
    TARGET_SPEED = SPEED_LIMIT
    RANGES = TwoWayOvertakeRanges
    DIFFICULTIES = DIFFICULTIES
    REMOVED_KEYS = frozenset({"other_vehicles_type"})
    OVERTAKE = True

    slow_vehicle: Vehicle

    # The reward's weights (_rewards). Not config keys: the config is part of every record's arm, and the reward
    # is no part of what a planner does. two-way-v0's own weight keys (high_speed_reward, left_lane_reward) stay
    # in the config, unread.
    REWARD_WEIGHTS = MappingProxyType({"high_speed_reward": 0.8, "right_lane_reward": 0.2, "goal_reward": 1.0})

    def _reward(self, action) -> float:
        return sum(self.REWARD_WEIGHTS[name] * term for name, term in self._rewards(action).items())

    def _rewards(self, action) -> dict[str, float]:
        """The reward's terms, weighted by :data:`REWARD_WEIGHTS` (0.8, 0.2, 1.0): for learners, as the planners
        never read it. two-way-v0's reward (:class:`bimp.envs.highway.fixed.FixedTwoWayEnv`'s, speed 20-30
        m/s and a left-lane term that is 0 on this road) pays nothing for the goal, which ends the episode: so a
        pass that returns to its lane cuts the reward short, and PPO trained on it raced on in the oncoming lane
        (1,000-1,550 m in the 40 s; 15 goals in 300 episodes). Here:

        - ``high_speed_reward``: the EV's speed per the speed limit, clipped to [0, 1];
        - ``right_lane_reward``: 1 on its own lane (centre within 1 m of the lane's, as the goal asks), else 0;
        - ``goal_reward``: at the step the goal is reached, the policy steps left before the time limit. The goal
          ends the episode, and must not cost the reward those steps would have earned (at most 1 each)."""
        right = self.road.network.get_lane(RIGHT)
        lateral = right.local_coordinates(self.vehicle.position)[1]
        left = max(self.config["duration"] - self.time, 0.0) * self.config["policy_frequency"]
        return {"high_speed_reward": min(max(float(self.vehicle.speed) / SPEED_LIMIT, 0.0), 1.0),
                "right_lane_reward": float(abs(lateral) <= 1.0),
                "goal_reward": float(left) if self.goal_reached() else 0.0}

    def _make_road(self, length: float = ROAD_LENGTH) -> None:
        super()._make_road(length)
        for lane in self.road.network.lanes_list():
            lane.speed_limit = SPEED_LIMIT

    def _make_vehicles(self) -> None:
        """The EV, the slow vehicle and the oncoming stream (module docstring), in that order of draws."""
        road, network = self.road, self.road.network
        ev_speed = self._draw("ev_speed")
        slow_speed, slow_distance = self._draw("slow_speed"), self._draw("slow_distance")
        first, until = self._draw("oncoming_first"), self._draw("oncoming_until")
        right = network.get_lane(RIGHT)
        self._add_ev(right, ev_speed)

        x = EV_X + slow_distance
        slow = IDMVehicle(road, right.position(x, 0.0), right.heading_at(x), slow_speed, target_lane_index=RIGHT,
                          target_speed=slow_speed, enable_lane_change=False)
        slow.color = SLOW_COLOUR
        self.slow_vehicle = slow
        road.vehicles.append(slow)

        oncoming = network.get_lane(ONCOMING)
        ahead, speeds = first, []
        while ahead <= until:
            s = ROAD_LENGTH - (EV_X + ahead)  # the oncoming lane runs from x = ROAD_LENGTH down to 0
            speed = float(self.np_random.uniform(*self.config["oncoming_speed"]))
            road.vehicles.append(IDMVehicle(road, oncoming.position(s, 0.0), oncoming.heading_at(s), speed,
                                            target_lane_index=ONCOMING, target_speed=speed,
                                            enable_lane_change=False))
            speeds.append(speed)
            ahead += float(self.np_random.uniform(*self.config["oncoming_gap"]))
        self.drawn_params["oncoming_count"] = len(speeds)

    def goal_reached(self) -> bool:
        """The slow vehicle passed: the EV in its lane again (centre within 1 m of the lane's), :data:`PASSED` m or
        more ahead of the slow vehicle's centre."""
        ev, right = self.vehicle, self.road.network.get_lane(RIGHT)
        s, lateral = right.local_coordinates(ev.position)
        return bool(abs(lateral) <= 1.0 and s - right.local_coordinates(self.slow_vehicle.position)[0] >= PASSED)
