"""The benchmark suite's scenario families (issue 27): highway-env envs with reactive traffic, documented randomized
ranges and a difficulty, driven by every bimp policy through the highway-env adapter.

One module per family (its env class, a :class:`bimp.envs.suite.family.Family`), and one entry per family in
:data:`FAMILIES` below. From that entry the adapter takes the family's class and its per-env numbers
(:data:`bimp.envs.highway.profiles.PROFILES` under the family's ``ID``), and the scenario table registers it as
``bimp/ID`` under the family's name (``bimp evaluate --scenario stalled-vehicle``,
``gym.make("bimp/stalled-vehicle-v0")``).

- :mod:`.stalled_vehicle`: ``stalled-vehicle``, a stopped vehicle in the EV's lane, traffic beside it;
- :mod:`.cut_in`: ``cut-in``, a vehicle in the next lane cuts in ahead of the EV at a short time gap and brakes;
- :mod:`.lane_drop`: ``lane-drop``, the EV's lane closed ahead (a construction zone), traffic in the lane to merge
  into;
- :mod:`.dense_highway`: ``dense-highway``, dense traffic with aggressive drivers, slower than the EV's target;
- :mod:`.erratic_traffic`: ``erratic-traffic``, traffic whose braking and lane changes carry heavy-tailed noise;
- :mod:`.two_way_overtake`: ``two-way-overtake``, pass a slow vehicle on a two-way road through gaps in the
  oncoming traffic, some too short;
- :mod:`.family`: what every family shares (difficulty, ranges, draws);
- the oracle that shows every instance leaves a safe plan: :mod:`bimp.envs.oracle`.
"""

from __future__ import annotations

from types import MappingProxyType

from bimp.envs.suite.cut_in import CutInEnv
from bimp.envs.suite.dense_highway import DenseHighwayEnv
from bimp.envs.suite.erratic_traffic import ErraticTrafficEnv
from bimp.envs.suite.family import Family
from bimp.envs.suite.lane_drop import LaneDropEnv
from bimp.envs.suite.stalled_vehicle import StalledVehicleEnv
from bimp.envs.suite.two_way_overtake import TwoWayOvertakeEnv

# The suite's table: family name -> env class. A new family is its module and one entry here.
FAMILIES: MappingProxyType[str, type[Family]] = MappingProxyType({
    cls.NAME: cls for cls in (
        StalledVehicleEnv,
        CutInEnv,
        LaneDropEnv,
        ErraticTrafficEnv,
        DenseHighwayEnv,
        TwoWayOvertakeEnv,
    )
})

__all__ = ["FAMILIES", "CutInEnv", "DenseHighwayEnv", "ErraticTrafficEnv", "Family", "LaneDropEnv",
           "StalledVehicleEnv", "TwoWayOvertakeEnv"]
