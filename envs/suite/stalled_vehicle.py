"""``stalled-vehicle`` (issue 27): a stopped vehicle (an accident site) in the EV's lane, traffic beside it; find a gap
or stop.

A straight road of ``lanes_count`` (default 3) lanes of 4 m, speed limit 30 m/s (highway-env's highway-v0 road). At
every ``reset(seed=...)``, from the env's own ``np_random``:

- the EV's lane, uniform among the lanes, and its speed (``ev_speed``), starting at x = 200 m on the lane's centre;
- the stalled vehicle: a plain highway-env ``Vehicle`` at speed 0 and no input (it never moves), ``stall_distance``
  ahead of the EV in its lane, centre to centre. No other vehicle starts in the EV's lane;
- traffic in every other lane, from 150 m behind the EV to 150 m past the stalled vehicle: ``density`` vehicles per km
  per lane on average (consecutive centre gaps of 1000 / density m, times a uniform factor in [0.7, 1.3], at least
  15 m: a car and IDM's 10 m jam distance), each at its own speed drawn from ``traffic_speed`` (its IDM target);
- the drivers: each traffic vehicle is a highway-env ``AggressiveVehicle`` with probability ``aggressive_share``, a
  ``DefensiveVehicle`` with probability ``defensive_share``, else an ``IDMVehicle`` whose IDM exponent is
  randomized as highway-v0 randomizes it (``randomize_behavior``); the shares are drawn once per episode.

Ranges per ``difficulty`` (:data:`DIFFICULTIES`; units as :class:`StalledVehicleRanges` says):

============  ============  ================  ================  ===============  ================  ===============
difficulty    ev_speed      stall_distance    density           traffic_speed    aggressive_share  defensive_share
============  ============  ================  ================  ===============  ================  ===============
easy          20 - 25       120 - 200         3 - 8             20 - 28          0 - 0.1           0.2 - 0.5
medium        22 - 28       90 - 150          8 - 16            20 - 28          0.1 - 0.3         0.1 - 0.3
hard          25 - 30       85 - 120          25 - 40           20 - 28          0.4 - 0.6         0 - 0.1
============  ============  ================  ================  ===============  ================  ===============

The densities are where highway-env's MOBIL finds its gaps or not: it changes lanes only where the new follower
brakes at most 2 m/s^2 for it, and never below 1 m/s. IDM/MOBIL (``make_policy("idm", env)``) passed the stall on
10 of 10 development episodes at 5 vehicles/km/lane, 6 of 10 at 10, 0 of 10 at 15 (easy's other ranges, seeds 0-9).
highway-env's ``AggressiveVehicle`` (a ``LinearVehicle``: acceleration linear in the speed and gap errors) comes to
rest with its centre 10 - 0.21 x its target speed [m] behind a standing leader, inside the 5 m of a car for targets
above 23.5 m/s: one that queues behind a stopped EV runs into it, a collision that ends the episode and is not the
EV's fault (a ``DefensiveVehicle`` rests 7.8 m or more behind).

Every instance leaves a safe plan inside the planning bounds: the EV can stop in its lane behind the stalled vehicle
by braking at the bounds from its first step (:func:`bimp.envs.oracle.stop_behind`), keeping at least ``d_min``
(1 m) between the footprints. A stopped EV that traffic runs into is not at fault (``docs/suite.md``). The check is
on the worst corner of the ranges (the fastest EV, the nearest stall), where the least gap is smallest: ranges whose
worst corner fails are refused (:class:`StalledVehicleRanges`), so a custom range never leaves the oracle's cover.
The oracle assumes that no traffic vehicle enters the EV's lane between the EV and the stalled vehicle while the EV
moves, which the tests check on whole episodes driven by the oracle's plan (seeds 0-99 per difficulty, a slow test):
it holds on easy and medium; on hard traffic entered there while the EV braked on 3 of 100 seeds (MOBIL's gain sees
the free lane before the stall), and the braking EV kept clear of it on each. Once the EV stands, traffic enters there
on hard more often (13 of 100 seeds), and highway-env's aggressive drivers rear-end the standing EV (26 of 100 seeds;
none on easy or medium): never the EV's fault, so the oracle's plan has no at-fault collision on any of the draws
driven, but success counts every collision, and on hard waiting is not always collision-free.

Success: the time limit (20 s) reached without collision or leaving the road (no goal: stopping behind the stalled
vehicle where no gap opens is a safe end); the score's progress part tells passing from waiting.
"""

from __future__ import annotations

import dataclasses
from types import MappingProxyType

from highway_env.envs.highway_env import HighwayEnv
from highway_env.vehicle.kinematics import Vehicle

from bimp.configs import ConfigError, check_fields
from bimp.envs.oracle import stop_behind
from bimp.envs.scene import Bounds
from bimp.envs.suite.family import EV_X, Envelope, HighwayFamily, check_ranges, check_shares

TRAFFIC_BEHIND, TRAFFIC_PAST = 150.0, 150.0  # m: traffic from this far behind the EV to this far past the stall
STALLED_COLOUR = (20, 20, 20)  # near black: no highway-env vehicle is drawn so (IDM blue, Linear yellow, crashed red)
BOUNDS = Bounds()

# Where each range may lie, whatever the difficulty: what the oracle and the road cover.
ENVELOPE = MappingProxyType({
    "ev_speed": Envelope(15.0, 30.0, "m/s", "the lanes' speed limit is 30 m/s; below 15 it is no longer a highway"),
    "stall_distance": Envelope(40.0, 250.0, "m", "centre to centre; the road a planner sees ends 250 m ahead"),
    "density": Envelope(0.0, 50.0, "vehicles/km/lane", "above 50 the 15 m least gap rules the spacing"),
    "traffic_speed": Envelope(15.0, 30.0, "m/s", "the lanes' speed limit is 30 m/s"),
    "aggressive_share": Envelope(0.0, 1.0, "", "a probability"),
    "defensive_share": Envelope(0.0, 1.0, "", "a probability"),
})


@dataclasses.dataclass(frozen=True)
class StalledVehicleRanges:
    """The family's randomized ranges, each ``(lo, hi)`` drawn uniformly at every reset: ``ev_speed`` [m/s],
    ``stall_distance`` [m] (the stalled vehicle's centre ahead of the EV's), ``density`` [vehicles per km per lane,
    in the lanes beside the EV's], ``traffic_speed`` [m/s, each traffic vehicle's], ``aggressive_share`` and
    ``defensive_share`` [probability of each traffic vehicle's kind]. Each inside :data:`ENVELOPE`; the two
    shares' highs sum to at most 1; and the worst corner (``ev_speed`` high, ``stall_distance`` low) leaves the
    oracle's stop at least ``d_min`` clear. ``ConfigError`` naming the range otherwise."""

    ev_speed: tuple[float, float]
    stall_distance: tuple[float, float]
    density: tuple[float, float]
    traffic_speed: tuple[float, float]
    aggressive_share: tuple[float, float]
    defensive_share: tuple[float, float]

    def __post_init__(self) -> None:
        check_fields(self)
        check_ranges(self, ENVELOPE)
        check_shares(self)
        gap = self.least_gap()
        if gap < BOUNDS.d_min:
            need = self.stall_distance[0] + BOUNDS.d_min - gap  # the least gap grows 1:1 with the stall distance
            raise ConfigError("stall_distance", f"a range whose low is at least {need:.1f} m with ev_speed up to "
                              f"{self.ev_speed[1]:g} m/s", self.stall_distance,
                              f"outside the oracle's cover: braking at the planning bounds from the first step "
                              f"stops {gap:.2f} m short of the stalled vehicle, d_min is {BOUNDS.d_min:g} m")

    def least_gap(self) -> float:
        """The oracle's least footprint gap [m] at the ranges' worst corner (the fastest EV, the nearest stall)."""
        return float(stop_behind(self.ev_speed[1], self.stall_distance[0], BOUNDS))


DIFFICULTIES = MappingProxyType({
    "easy": StalledVehicleRanges(ev_speed=(20.0, 25.0), stall_distance=(120.0, 200.0), density=(3.0, 8.0),
                                 traffic_speed=(20.0, 28.0), aggressive_share=(0.0, 0.1),
                                 defensive_share=(0.2, 0.5)),
    "medium": StalledVehicleRanges(ev_speed=(22.0, 28.0), stall_distance=(90.0, 150.0), density=(8.0, 16.0),
                                   traffic_speed=(20.0, 28.0), aggressive_share=(0.1, 0.3),
                                   defensive_share=(0.1, 0.3)),
    "hard": StalledVehicleRanges(ev_speed=(25.0, 30.0), stall_distance=(85.0, 120.0), density=(25.0, 40.0),
                                 traffic_speed=(20.0, 28.0), aggressive_share=(0.4, 0.6),
                                 defensive_share=(0.0, 0.1)),
})


class StalledVehicleEnv(HighwayFamily, HighwayEnv):
    """The ``stalled-vehicle`` family (module docstring): highway-env's ``HighwayEnv`` road with the family's own
    population. ``self.stalled_vehicle``: the standing vehicle of this episode. Config: highway-env's keys but those
    its population replaces (:attr:`REMOVED_KEYS`), ``lanes_count`` an int in [2, 5], ``difficulty`` and the
    ranges of :class:`StalledVehicleRanges`."""

    NAME = "stalled-vehicle"
    ID = "stalled-vehicle-v0"
    DURATION = 20.0  # s: the farthest stall (200 m at 20 m/s) is reached after 10 s, with time left to pass it
    TARGET_SPEED = 30.0  # m/s: the lanes' speed limit, as highway-v0's profile
    RANGES = StalledVehicleRanges
    DIFFICULTIES = DIFFICULTIES
    LANES_WHY = "a lane beside the stall to pass in"

    stalled_vehicle: Vehicle

    def _create_vehicles(self) -> None:
        """The EV, the stalled vehicle and the traffic (module docstring), in that order of draws."""
        road, network = self.road, self.road.network
        lanes = network.graph["0"]["1"]
        ev_lane = int(self.np_random.integers(len(lanes)))
        self.drawn_params["ev_lane"] = ev_lane
        ev_speed = self._draw("ev_speed")
        stall = self._draw("stall_distance")
        density = self._draw("density")
        aggressive, defensive = self._draw("aggressive_share"), self._draw("defensive_share")

        lane = lanes[ev_lane]
        self._add_ev(lane, ev_speed)
        stalled = Vehicle(road, lane.position(EV_X + stall, 0.0), lane.heading_at(EV_X + stall), 0.0)
        stalled.color = STALLED_COLOUR  # an accident site; also keeps highway-env from drawing it as traffic
        self.stalled_vehicle = stalled
        road.vehicles.append(stalled)

        self._place_traffic(lanes, EV_X - TRAFFIC_BEHIND, EV_X + stall + TRAFFIC_PAST, density, aggressive,
                            defensive, skip=(ev_lane,))
