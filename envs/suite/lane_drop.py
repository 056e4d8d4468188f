"""``lane-drop`` (issue 27): the EV's lane ends (a construction zone) with traffic in the lane it must merge into.

A straight road of ``lanes_count`` (default 3) lanes of 4 m, speed limit 30 m/s (highway-env's highway-v0 road). The
EV's lane is closed ahead by a row of highway-env ``Obstacle`` blocks (:class:`ClosureBlock`, a car's 5 m x 2 m), as
merge-v0 closes its ending lane with an ``Obstacle``: every lane of the road stays in the network, so the adapter's
road edges are the straight road's, and the closure is what the EV, the planners (the blocks are OV rows of the
observation, speed 0) and the behaviour layer (highway-env's IDM brakes for a road object ahead, MOBIL leaves its
lane for it) see. At every ``reset(seed=...)``, from the env's own ``np_random``:

- the EV's lane, uniform between the two outer lanes (a lane drop ends an outer lane; the lane beside it is the one
  to merge into), and its speed (``ev_speed``), starting at x = 200 m on the lane's centre;
- the closure: :data:`CLOSURE_BLOCKS` blocks every :data:`BLOCK_SPACING` m along the EV's lane's centre, the first
  ``drop_distance`` ahead of the EV (centre to centre): a closed stretch of 150 m that no car fits through;
- traffic in every other lane as in ``stalled-vehicle``, from 150 m behind the EV to 150 m past the closure's end:
  ``density`` vehicles per km per lane (centre gaps of 1000 / density m times a uniform factor in [0.7, 1.3], at
  least 15 m), each at its own speed from ``traffic_speed``, each an ``AggressiveVehicle`` with probability
  ``aggressive_share``, a ``DefensiveVehicle`` with probability ``defensive_share``, else an ``IDMVehicle``. No
  traffic starts in the EV's lane.

Not a real lane end: highway-env's straight road would need its own network (a lane that ends, as merge-v0's ramp)
and the adapter's road edges would have to follow it; the closure is a row of standing blocks instead. It differs
from ``stalled-vehicle``'s stall: the lane is closed for 150 m, not 5 m, so waiting behind it never clears the way
and the closed lane is no shelter for traffic either; the traffic beside it is denser (35 - 50 vehicles/km/lane on
hard, against 25 - 40); and the closed lane is an outer one, so there is one lane to merge into.

Ranges per ``difficulty`` (:data:`DIFFICULTIES`; ``traffic_speed`` 20 - 28 m/s throughout):

==========  ========  =============  =======  ================  ===============
difficulty  ev_speed  drop_distance  density  aggressive_share  defensive_share
==========  ========  =============  =======  ================  ===============
easy        20 - 25   150 - 230      5 - 10   0 - 0.1           0.2 - 0.5
medium      22 - 28   110 - 180      12 - 20  0.1 - 0.3         0.1 - 0.3
hard        25 - 30   82 - 110       35 - 50  0.4 - 0.6         0 - 0.1
==========  ========  =============  =======  ================  ===============

Every instance leaves a safe plan inside the planning bounds: the EV can stop in its lane behind the closure's first
block by braking at the bounds from its first step (:func:`bimp.envs.oracle.stop_behind`; the block has a car's
length, so the oracle's footprint gap is the env's), keeping at least ``d_min`` (1 m). Ranges whose worst corner
(the fastest EV, the nearest closure) fails are refused (:class:`LaneDropRanges`). The oracle assumes no traffic enters
the EV's lane between the EV and the closure while the EV moves; a slow test counts and bounds where it breaks, on whole
episodes driven by the oracle's plan (seeds 0-99 per difficulty). It does not always hold: MOBIL sends traffic into the
closed lane's free stretch while the EV brakes (1 of 100 easy seeds, 8 medium, 3 hard, when written), where it stands
against the closure ahead of the EV; the braking EV kept clear of it on all of them. On hard, aggressive drivers
rear-end the standing EV (27 of 100 seeds; 1 on medium, none on easy): never the EV's fault, but success counts it.

Success: the time limit (20 s) reached without collision or leaving the road (no goal: stopping behind the closure
where no gap opens is a safe end); the score's progress part tells merging from waiting.
"""

from __future__ import annotations

import dataclasses
from types import MappingProxyType

from highway_env.envs.highway_env import HighwayEnv
from highway_env.vehicle.objects import Obstacle

from bimp.configs import ConfigError, check_fields
from bimp.envs.oracle import stop_behind
from bimp.envs.scene import VEHICLE_LENGTH, VEHICLE_WIDTH, Bounds
from bimp.envs.suite.family import EV_X, Envelope, HighwayFamily, check_ranges, check_shares

TRAFFIC_BEHIND, TRAFFIC_PAST = 150.0, 150.0  # m: traffic from this far behind the EV to this far past the closure
CLOSURE_BLOCKS = 21  # blocks in the closure's row
BLOCK_SPACING = 7.5  # m, centre to centre: 2.5 m between 5 m blocks, no car fits between
CLOSURE_LENGTH = (CLOSURE_BLOCKS - 1) * BLOCK_SPACING  # 150 m, first block's centre to the last's
BOUNDS = Bounds()


class ClosureBlock(Obstacle):
    """A construction-zone block: highway-env's ``Obstacle`` (a standing road object, as merge-v0's lane end) with a
    car's footprint, so that the planners' OV model of it (a car) is its true size."""

    LENGTH = VEHICLE_LENGTH
    WIDTH = VEHICLE_WIDTH


ENVELOPE = MappingProxyType({
    "ev_speed": Envelope(15.0, 30.0, "m/s", "the lanes' speed limit is 30 m/s; below 15 it is no longer a highway"),
    "drop_distance": Envelope(40.0, 250.0, "m", "centre to centre; the road a planner sees ends 250 m ahead"),
    "density": Envelope(0.0, 50.0, "vehicles/km/lane", "above 50 the 15 m least gap rules the spacing"),
    "traffic_speed": Envelope(15.0, 30.0, "m/s", "the lanes' speed limit is 30 m/s"),
    "aggressive_share": Envelope(0.0, 1.0, "", "a probability"),
    "defensive_share": Envelope(0.0, 1.0, "", "a probability"),
})


@dataclasses.dataclass(frozen=True)
class LaneDropRanges:
    """The family's randomized ranges, each ``(lo, hi)`` drawn uniformly at every reset: ``ev_speed`` [m/s],
    ``drop_distance`` [m] (the closure's first block's centre ahead of the EV's), ``density`` [vehicles per km per
    lane, in the lanes beside the EV's], ``traffic_speed`` [m/s], ``aggressive_share`` and ``defensive_share``
    [probability of each traffic vehicle's kind]. Each inside :data:`ENVELOPE`; the shares' highs sum to at most 1;
    the worst corner (``ev_speed`` high, ``drop_distance`` low) leaves the oracle's stop at least ``d_min`` clear.
    ``ConfigError`` naming the range otherwise."""

    ev_speed: tuple[float, float]
    drop_distance: tuple[float, float]
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
            need = self.drop_distance[0] + BOUNDS.d_min - gap  # the least gap grows 1:1 with the distance
            raise ConfigError("drop_distance", f"a range whose low is at least {need:.1f} m with ev_speed up to "
                              f"{self.ev_speed[1]:g} m/s", self.drop_distance,
                              f"outside the oracle's cover: braking at the planning bounds from the first step "
                              f"stops {gap:.2f} m short of the closure, d_min is {BOUNDS.d_min:g} m")

    def least_gap(self) -> float:
        """The oracle's least footprint gap [m] at the ranges' worst corner (the fastest EV, the nearest closure)."""
        return float(stop_behind(self.ev_speed[1], self.drop_distance[0], BOUNDS))


DIFFICULTIES = MappingProxyType({
    "easy": LaneDropRanges(ev_speed=(20.0, 25.0), drop_distance=(150.0, 230.0), density=(5.0, 10.0),
                           traffic_speed=(20.0, 28.0), aggressive_share=(0.0, 0.1), defensive_share=(0.2, 0.5)),
    "medium": LaneDropRanges(ev_speed=(22.0, 28.0), drop_distance=(110.0, 180.0), density=(12.0, 20.0),
                             traffic_speed=(20.0, 28.0), aggressive_share=(0.1, 0.3), defensive_share=(0.1, 0.3)),
    "hard": LaneDropRanges(ev_speed=(25.0, 30.0), drop_distance=(82.0, 110.0), density=(35.0, 50.0),
                           traffic_speed=(20.0, 28.0), aggressive_share=(0.4, 0.6), defensive_share=(0.0, 0.1)),
})


class LaneDropEnv(HighwayFamily, HighwayEnv):
    """The ``lane-drop`` family (module docstring): highway-env's ``HighwayEnv`` road, the EV's outer lane closed
    ahead. ``self.closure``: this episode's blocks, nearest first. Config: highway-env's keys but those the
    population replaces (:attr:`REMOVED_KEYS`), ``lanes_count`` an int in [2, 5], ``difficulty`` and the ranges of
    :class:`LaneDropRanges`."""

    NAME = "lane-drop"
    ID = "lane-drop-v0"
    DURATION = 20.0  # s: the farthest closure (230 m at 20 m/s) is reached after 11.5 s
    TARGET_SPEED = 30.0  # m/s: the lanes' speed limit
    RANGES = LaneDropRanges
    DIFFICULTIES = DIFFICULTIES
    LANES_WHY = "a lane beside the closed one to merge into"

    closure: list[ClosureBlock]

    def _create_vehicles(self) -> None:
        """The EV, the closure and the traffic (module docstring), in that order of draws."""
        road, network = self.road, self.road.network
        lanes = network.graph["0"]["1"]
        ev_lane = (0, len(lanes) - 1)[int(self.np_random.integers(2))]
        self.drawn_params["ev_lane"] = ev_lane
        ev_speed = self._draw("ev_speed")
        drop = self._draw("drop_distance")
        density = self._draw("density")
        aggressive, defensive = self._draw("aggressive_share"), self._draw("defensive_share")

        lane = lanes[ev_lane]
        self._add_ev(lane, ev_speed)
        self.closure = []
        for k in range(CLOSURE_BLOCKS):
            x = EV_X + drop + k * BLOCK_SPACING
            block = ClosureBlock(road, lane.position(x, 0.0), lane.heading_at(x))
            self.closure.append(block)
            road.objects.append(block)

        self._place_traffic(lanes, EV_X - TRAFFIC_BEHIND, EV_X + drop + CLOSURE_LENGTH + TRAFFIC_PAST, density,
                            aggressive, defensive, skip=(ev_lane,))
