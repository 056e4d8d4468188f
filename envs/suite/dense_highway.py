"""``dense-highway`` (issue 27): dense traffic with aggressive drivers mixed in, slower than the EV's target speed;
hold the target speed by weaving through it, or follow.

A straight road of ``lanes_count`` (default 3) lanes of 4 m, speed limit 30 m/s (highway-env's highway-v0 road). At
every ``reset(seed=...)``, from the env's own ``np_random``:

- the EV's lane, uniform among the lanes, and its speed (``ev_speed``), starting at x = 200 m on the lane's centre;
- the leader: a traffic vehicle ``leader_gap`` ahead of the EV in its lane (centre to centre), its kind and speed
  drawn as every traffic vehicle's (below);
- traffic in every lane, the EV's included, from 100 m behind the EV to 300 m ahead: ``density`` vehicles per km
  per lane (centre gaps of 1000 / density m times a uniform factor in [0.7, 1.3], at least 15 m: a car and IDM's
  10 m jam distance), each at its own speed drawn from ``traffic_speed`` (its IDM target); none starts in the EV's
  lane from :data:`REAR_CLEAR` behind the EV to 15 m past the leader, so that the leader is the vehicle ahead and
  the nearest follower is at least that far behind;
- the drivers: each traffic vehicle (the leader too) is a highway-env ``AggressiveVehicle`` with probability
  ``aggressive_share``, a ``DefensiveVehicle`` with probability ``defensive_share``, else an ``IDMVehicle`` whose
  IDM exponent is randomized as highway-v0 randomizes it; the shares are drawn once per episode.

The EV's target (:attr:`DenseHighwayEnv.TARGET_SPEED`, the behaviour layer's free-road target) is the lanes' limit,
30 m/s, above every traffic speed: holding it means passing, lane after lane, through traffic in every lane (the
EV's own included) at least as dense as any other family's lanes at each difficulty (lane-drop's hard reaches the
same 50 vehicles/km/lane beside its closure), where aggressive drivers (highway-env's ``AggressiveVehicle``: MOBIL
with no politeness, a linear car-following law that closes to within a car's length of a standing leader at targets
above 23.5 m/s) change lanes in front of it and close up behind it. At these densities highway-env's IDM traffic does
not flow at its targets (IDM's desired gap at 20 m/s is 40 m, bumper to bumper; 40 vehicles/km/lane leave 20 m):
it slows within seconds to 10-15 m/s, in stop-and-go waves on hard, so ``traffic_speed`` is each vehicle's target
and its speed at reset, not its speed later.

Ranges per ``difficulty`` (:data:`DIFFICULTIES`; units as :class:`DenseHighwayRanges` says):

==========  ========  ==========  =======  =============  ================  ===============
difficulty  ev_speed  leader_gap  density  traffic_speed  aggressive_share  defensive_share
==========  ========  ==========  =======  =============  ================  ===============
easy        20 - 25   45 - 80     14 - 20  18 - 26        0.1 - 0.2         0.2 - 0.4
medium      22 - 27   50 - 75     24 - 34  16 - 25        0.2 - 0.4         0.1 - 0.3
hard        24 - 28   55 - 70     40 - 50  15 - 26        0.5 - 0.7         0 - 0.2
==========  ========  ==========  =======  =============  ================  ===============

Every instance leaves a safe plan inside the planning bounds: the EV brakes in its lane at the planning bounds from
its first step (:func:`bimp.envs.oracle.brake_at_the_bounds`: -1 m/s^2 more per step down to -7 m/s^2, to a stop)
while its leader brakes to a stop from the first step at :data:`LEADER_DECEL` (6 m/s^2, highway-env's
``IDMVehicle.ACC_MAX``: ``IDMVehicle.act`` clips every IDM vehicle's acceleration to it, and the Linear kinds,
aggressive and defensive, act through it too, so no traffic vehicle brakes harder unless it has crashed), keeping
at least ``d_min`` (1 m) between the footprints. The least gap grows with the leader's gap and speed and shrinks with
the EV's speed (each vehicle's path is monotone in its start), so the worst corner of the ranges is the fastest EV
behind the slowest leader at the nearest gap: ranges whose worst corner the plan does not keep ``d_min`` clear are
refused naming ``leader_gap`` (:class:`DenseHighwayRanges`). A standing EV that traffic runs into is not at fault
(``docs/suite.md``). What the oracle does not cover (``docs/suite.md`` counts it on the oracle's plan driven in
the env):
traffic changing into the EV's lane between the EV and its leader (MOBIL, whose safety rule for its new follower,
the EV, only bounds the follower's IDM braking at 2 m/s^2), a leader that crashes into its own leader (highway-env
stops a crashed vehicle at its speed per second, harder than 6 m/s^2), a leader that backs up (highway-env's IDM
reverses where it stands too near what is ahead: its speed is not clamped at 0), OV-OV crashes (aggressive drivers
run into a queue), and traffic running into the braking or standing EV, never the EV's fault.

Success: the time limit (15 s) reached without collision or leaving the road (no goal); the score's progress and
speed parts tell weaving at the target from following.
"""

from __future__ import annotations

import dataclasses
from types import MappingProxyType

import numpy as np
from highway_env.envs.highway_env import HighwayEnv
from highway_env.vehicle.behavior import IDMVehicle
from numpy.typing import ArrayLike

from bimp.configs import check_fields
from bimp.envs.oracle import brake_at_the_bounds
from bimp.envs.scene import Bounds
from bimp.envs.suite.family import (
    EV_X,
    MIN_TRAFFIC_GAP,
    Envelope,
    HighwayFamily,
    check_leader_gap,
    check_ranges,
    check_shares,
    traffic_kind,
)

# m: traffic from this far behind the EV to this far ahead of it. Ahead: traffic 300 m ahead at 18 m/s is still
# ahead of an EV at 30 m/s after 15 s. Not more: highway-env's step costs the square of the vehicles' count.
TRAFFIC_BEHIND, TRAFFIC_AHEAD = 100.0, 300.0
REAR_CLEAR = 30.0  # m, centre to centre: no traffic starts nearer behind the EV in its lane (a 1 s gap at 25 m/s)
LEADER_DECEL = float(IDMVehicle.ACC_MAX)  # m/s^2: the hardest braking of highway-env's IDM and Linear vehicles
BOUNDS = Bounds()


def least_gap(ev_speed: ArrayLike, leader_gap: ArrayLike, leader_speed: ArrayLike,
              bounds: Bounds | None = None) -> np.ndarray:
    """The oracle's least footprint gap [m] ``(...)`` to the leader: the EV (``ev_speed`` [m/s], last input 0)
    brakes at the planning bounds from its first step while the leader (``leader_gap`` [m] ahead, centre to centre,
    at ``leader_speed`` [m/s]) brakes at :data:`LEADER_DECEL` to a stop from the first step. Arrays broadcast."""
    return brake_at_the_bounds(ev_speed, leader_gap, leader_speed, 0.0, LEADER_DECEL, react=False,
                               bounds=BOUNDS if bounds is None else bounds)


# Where each range may lie, whatever the difficulty: what the oracle and the road cover.
ENVELOPE = MappingProxyType({
    "ev_speed": Envelope(15.0, 30.0, "m/s", "the lanes' speed limit is 30 m/s; below 15 it is no longer a highway"),
    "leader_gap": Envelope(20.0, 150.0, "m", "centre to centre; beyond 150 m the EV has no leader to weave past"),
    "density": Envelope(0.0, 50.0, "vehicles/km/lane", "above 50 the 15 m least gap rules the spacing"),
    "traffic_speed": Envelope(15.0, 30.0, "m/s", "the lanes' speed limit is 30 m/s"),
    "aggressive_share": Envelope(0.0, 1.0, "", "a probability"),
    "defensive_share": Envelope(0.0, 1.0, "", "a probability"),
})


@dataclasses.dataclass(frozen=True)
class DenseHighwayRanges:
    """The family's randomized ranges, each ``(lo, hi)`` drawn uniformly at every reset: ``ev_speed`` [m/s],
    ``leader_gap`` [m] (the leader's centre ahead of the EV's), ``density`` [vehicles per km per lane, every lane],
    ``traffic_speed`` [m/s, each traffic vehicle's, the leader's too], ``aggressive_share`` and ``defensive_share``
    [probability of each traffic vehicle's kind]. Each inside :data:`ENVELOPE`; the shares' highs sum to at most 1;
    the worst corner (``ev_speed`` high, ``leader_gap`` and ``traffic_speed`` low) leaves the oracle at least
    ``d_min`` clear. ``ConfigError`` naming the range otherwise."""

    ev_speed: tuple[float, float]
    leader_gap: tuple[float, float]
    density: tuple[float, float]
    traffic_speed: tuple[float, float]
    aggressive_share: tuple[float, float]
    defensive_share: tuple[float, float]

    def __post_init__(self) -> None:
        check_fields(self)
        check_ranges(self, ENVELOPE)
        check_shares(self)
        check_leader_gap(self, self.least_gap(), BOUNDS.d_min, f"braking at {LEADER_DECEL:g} m/s^2")

    def least_gap(self) -> float:
        """The oracle's least footprint gap [m] at the ranges' worst corner (the fastest EV, the nearest and slowest
        leader)."""
        return float(least_gap(self.ev_speed[1], self.leader_gap[0], self.traffic_speed[0]))


DIFFICULTIES = MappingProxyType({
    "easy": DenseHighwayRanges(ev_speed=(20.0, 25.0), leader_gap=(45.0, 80.0), density=(14.0, 20.0),
                               traffic_speed=(18.0, 26.0), aggressive_share=(0.1, 0.2), defensive_share=(0.2, 0.4)),
    "medium": DenseHighwayRanges(ev_speed=(22.0, 27.0), leader_gap=(50.0, 75.0), density=(24.0, 34.0),
                                 traffic_speed=(16.0, 25.0), aggressive_share=(0.2, 0.4),
                                 defensive_share=(0.1, 0.3)),
    "hard": DenseHighwayRanges(ev_speed=(24.0, 28.0), leader_gap=(55.0, 70.0), density=(40.0, 50.0),
                               traffic_speed=(15.0, 26.0), aggressive_share=(0.5, 0.7), defensive_share=(0.0, 0.2)),
})


class DenseHighwayEnv(HighwayFamily, HighwayEnv):
    """The ``dense-highway`` family (module docstring): highway-env's ``HighwayEnv`` road with the family's own
    population. ``self.leader``: this episode's vehicle ahead of the EV in its lane at reset. Config: highway-env's
    keys but those its population replaces (:attr:`REMOVED_KEYS`), ``lanes_count`` an int in [2, 5],
    ``difficulty`` and the ranges of :class:`DenseHighwayRanges`."""

    NAME = "dense-highway"
    ID = "dense-highway-v0"
    DURATION = 15.0  # s: at 30 m/s the EV covers 450 m, passing traffic 4-12 m/s slower by 60-180 m
    TARGET_SPEED = 30.0  # m/s: the lanes' speed limit, as highway-v0's profile
    RANGES = DenseHighwayRanges
    DIFFICULTIES = DIFFICULTIES
    LANES_WHY = "a lane beside the EV's to pass in"

    leader: IDMVehicle

    def _create_vehicles(self) -> None:
        """The EV, the leader and the traffic (module docstring), in that order of draws."""
        lanes = self.road.network.graph["0"]["1"]
        ev_lane = int(self.np_random.integers(len(lanes)))
        self.drawn_params["ev_lane"] = ev_lane
        ev_speed = self._draw("ev_speed")
        leader_gap = self._draw("leader_gap")
        density = self._draw("density")
        aggressive, defensive = self._draw("aggressive_share"), self._draw("defensive_share")

        lane = self.road.network.get_lane(("0", "1", ev_lane))
        self._add_ev(lane, ev_speed)
        self.leader = self._traffic_vehicle(lane, EV_X + leader_gap, aggressive, defensive)
        self.drawn_params.update(leader_speed=float(self.leader.speed), leader_kind=traffic_kind(self.leader))

        keep_out = {ev_lane: [(EV_X - REAR_CLEAR, EV_X + leader_gap + MIN_TRAFFIC_GAP)]}
        self._place_traffic(lanes, EV_X - TRAFFIC_BEHIND, EV_X + TRAFFIC_AHEAD, density, aggressive, defensive,
                            keep_out=keep_out)
