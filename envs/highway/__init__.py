"""highway-env's envs as bimp envs (issue 26): :func:`wrap` (also ``bimp.envs.wrap``) turns ``gym.make(ID)`` of a
supported id into an env every bimp policy drives; each id is also registered as ``bimp/ID``.

- :mod:`.adapter`: the adapter (:class:`HighwayAdapter`) and its entry points;
- :mod:`.profiles`: the adapter's per-id table (:data:`PROFILES`);
- :mod:`.fixed`: the adapted env classes, and the subclasses that fix highway-env's failures under continuous
  actions (merge, roundabout, two-way, u-turn);
- :mod:`.behaviour`: the behaviour layer (highway-env's IDM + MOBIL shadowing the EV);
- :mod:`.lanes`: the road ahead of the EV from highway-env's lane graph, as a :class:`bimp.envs.road.Route`.
"""

from bimp.envs.highway.adapter import PROFILES, SUPPORTED, HighwayAdapter, wrap

__all__ = ["PROFILES", "SUPPORTED", "HighwayAdapter", "wrap"]
