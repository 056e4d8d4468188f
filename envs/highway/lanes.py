"""The road ahead of the EV read from highway-env's lane graph, as the :class:`bimp.envs.road.Route` a planner knows.

The route polyline is the centreline of a lane continued along a route through the lane graph (highway-env's own
``RoadNetwork.next_lane``: the planned route where the vehicle has one, else the successor lane nearest to where
the lane ends), sampled every ``spacing`` m from ``behind`` m before a point to ``ahead`` m after it, and padded
straight past the end of the network (a route that ends mid-horizon is padded, never NaN). Its edges at each point
are the outer sides of the lanes beside it: every lane of the same road ``(from, to)``, of the reverse road
``(to, from)`` where the network has one (two-way roads: the oncoming lane is drivable), and of the roads merging into
``to`` or diverging from ``from`` where they run beside it (junctions), as signed lateral offsets
in the route's frame (``l`` > 0 to the right of travel, highway-env's +y at heading 0).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import numpy as np
from highway_env.road.lane import CircularLane
from highway_env.road.road import RoadNetwork

from bimp.envs.road import Route, wrap_angle

BEHIND, AHEAD, SPACING = 30.0, 250.0, 1.0  # m
EDGE_EVERY = 5  # edges are measured at every 5th point (every 5 m) and interpolated: lanes are smooth at that scale
MAX_LANES = 64  # a lane graph walk longer than this is a cycle walked again (racetrack): stop there
NEAR = 30.0  # m: a lane whose centre is further to the side than this is not beside the route
JOIN = 2.0  # m: a next lane that starts within this of where the lane ends continues it
BRIDGE = 8.0  # m: ... or within this, straight on (see joins)
# m: of lane either side of a bridged gap that the blend across it replaces (smooth_bridges). On roundabout-v0 7 m
# keeps the blends at its entry and exit 1.49 m or more from their edges (a car's half width, the barrier's 0.3 m
# margin and more) at radii of 8 m or more over 5 m (0.58 rad of steering); 6 m turns at 7.4 m (0.62 rad), 8 m comes
# within 1.39 m of the edges.
BLEND = 7.0


def lane_walk(network, index, s_from: float, length: float, route=None, spacing: float = SPACING):
    """Points along lane ``index`` from its arc length ``s_from`` for ``length`` m, continuing into the next lanes
    (``network.next_lane`` along a copy of ``route``): ``(xy (P, 2), heading (P,) wrapped, lanes (P,) list of lane
    indices, bridges: (i, j) index pairs, the last point of a lane and the first of the next where a gap of more
    than ``JOIN`` m between them was bridged)``; fewer metres where the network ends."""
    plan = list(route) if route else None  # next_lane pops the route's first road as it goes: never the vehicle's
    xy, heading, lanes, bridges = [], [], [], []
    s, remaining = s_from, length
    for _ in range(MAX_LANES):
        lane = network.get_lane(index)
        end = min(lane.length, s + remaining)
        for si in np.append(np.arange(s, end, spacing), end):
            xy.append(lane.position(si, 0.0))
            heading.append(lane.heading_at(si))
            lanes.append(index)
        remaining -= max(end - s, 0.0)
        if remaining <= 1e-6:
            break
        end_xy, end_heading = lane.position(lane.length, 0.0), lane.heading_at(lane.length)
        if plan and not (tuple(plan[0][:2]) == tuple(index[:2]) or plan[0][0] == index[1]):
            plan = None  # the walk has left the route: the lane graph's own choice (and no warning from highway-env)
        following = network.next_lane(index, route=plan, position=end_xy)
        if goes_on_beside(network, index, following):
            # The route's next road goes on from another lane of this one (exit-v0: the exit leaves from the right
            # lane, 24 m to the side): walk the lane that goes on from here; the lane change is the reference's.
            following = network.next_lane(index, route=None, position=end_xy)
        if following == index or following[1] == index[0] or not joins(network, following, end_xy, end_heading):
            break  # the end of the network, or a way back (past an intersection's exit road): padded straight
        # Go on from abreast of where this lane ended: lanes may overlap at a join (racetrack-v0: by 0.44 m, and the
        # polyline ran backwards there).
        s = max(0.0, float(coordinates(network.get_lane(following), end_xy)[0]))
        start = network.get_lane(following).position(s, 0.0)
        gap = float(np.hypot(*(start - end_xy)))
        if gap > JOIN:
            bridges.append((len(xy) - 1, len(xy) + len(np.arange(spacing, gap, spacing))))
        for f in np.arange(spacing, gap, spacing) / gap:  # a bridged gap (see joins), sampled like a lane
            xy.append(end_xy + f * (start - end_xy))
            heading.append(float(np.arctan2(*(start - end_xy)[::-1])))
            lanes.append(index)
        index = following
    return np.asarray(xy, float), np.asarray(heading, float), lanes, bridges


def smooth_bridges(network, xy: np.ndarray, heading: np.ndarray, lanes: list, bridges: list,
                   spacing: float = SPACING, reach: float = BLEND) -> tuple[np.ndarray, np.ndarray, list, np.ndarray]:
    """The walk's points with each bridged gap and ``reach`` m of lane either side replaced by a blend of the two
    lanes, each continued across the gap (``lane.position`` past its end or before its start): from the lane
    before to the lane after by a smoothstep weight over the window, sampled every ``spacing`` m. Returns ``xy
    (P', 2)``, ``heading (P',)``, ``lanes`` (each point's lane: the nearer of the two) and ``offset (P',)`` (each
    point's lateral offset from its lane's centre, 0 off the blends). A chord across the gap turns by up to 0.54
    rad within a metre (roundabout-v0's entry meets the ring 5.6 m on, at 47 degrees): no vehicle follows that,
    the heading and curvature terms of the planning problem read it as a wall, and the planners stopped at the
    entry for good."""
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    pieces, done = [], -np.inf
    for i, j in bridges:
        # The window and the weight are the lanes' own, wherever on the lane before the gap the walk starts: a route
        # rebuilt there lies on the one built before it. (One built from the lane after the gap does not see the
        # gap; the EV's kept route, built before it got there, is the blended one.)
        first, last = s[i] - reach, s[min(j, len(s) - 1)] + reach
        if first < done or j >= len(s) or last > s[-1]:  # overlapping the previous blend, or past the walk's end
            continue
        before, after = network.get_lane(lanes[i]), network.get_lane(lanes[j])
        s_before = coordinates(before, xy[i])[0]
        s_after = coordinates(after, xy[j])[0]
        a, b = int(np.searchsorted(s, first)), int(np.searchsorted(s, last))
        sigma = np.arange(max(first, s[0]), s[b], spacing / 20.0)  # to the walk's next point: segments <= spacing
        u = np.minimum((sigma - first) / (last - first), 1.0)
        w = (3 * u ** 2 - 2 * u ** 3)[:, None]
        dense = ((1 - w) * np.array([before.position(s_before + d, 0.0) for d in sigma - s[i]])
                 + w * np.array([after.position(s_after + d, 0.0) for d in sigma - s[j]]))
        arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(dense, axis=0).T))])
        at = np.arange(0.0, arc[-1], spacing)
        curve = np.stack([np.interp(at, arc, dense[:, 0]), np.interp(at, arc, dense[:, 1])], axis=1)
        step = np.gradient(curve, axis=0) if len(curve) > 1 else np.array([[np.cos(heading[i]), np.sin(heading[i])]])
        fits = np.array([[before.local_coordinates(p)[1], after.local_coordinates(p)[1]] for p in curve])
        nearer = np.abs(fits).argmin(axis=1)
        pieces.append((a, b, (curve, np.unwrap(np.arctan2(step[:, 1], step[:, 0])),
                              [(lanes[i], lanes[j])[n] for n in nearer], fits[np.arange(len(curve)), nearer])))
        done = s[b]  # the piece runs to the walk's point at or past its window's end
    offset, parts, k = np.zeros(len(xy)), [], 0
    for a, b, piece in pieces:  # the walk's points up to each blend, then the blend in their place
        parts += [(xy[k:a], heading[k:a], lanes[k:a], offset[k:a]), piece]
        k = b
    parts.append((xy[k:], heading[k:], lanes[k:], offset[k:]))
    xys, headings, lane_lists, offsets = zip(*parts)
    return (np.concatenate(xys), np.concatenate(headings), [lane for part in lane_lists for lane in part],
            np.concatenate(offsets))


def _spaced(xy: np.ndarray, least: float) -> np.ndarray:
    """Mask ``(P,)`` keeping the first point and every one at least ``least`` m from the last kept: a stub segment
    (a lane's last sample a few mm before its end) has a chord direction of no meaning, and projection divides by
    its length."""
    keep, last = np.zeros(len(xy), bool), None
    # Up to the first step shorter than ``least`` every point is kept (each is then measured from the one before it,
    # as the loop below would): only the rest needs the loop.
    short = np.flatnonzero(np.hypot(*np.diff(xy, axis=0).T) < least)
    head = len(xy) if not len(short) else int(short[0]) + 1
    keep[:head] = True
    last = xy[head - 1] if head else None
    for i in range(head, len(xy)):
        if last is None or np.hypot(*(xy[i] - last)) >= least:
            keep[i], last = True, xy[i]
    return keep


def joins(network: RoadNetwork, index: tuple, end: np.ndarray, heading: float) -> bool:
    """Whether lane ``index`` goes on from a lane that ends at ``end (2,)`` with ``heading``: it starts there (within
    ``JOIN`` m), or a little ahead (within ``BRIDGE`` m, roundabout-v0's entries meet the ring 5.6 m on) with the gap
    and its own start heading within 45 degrees of the way on; not a lane beside (exit-v0's exit road, 24 m to the
    side) nor one turning back."""
    lane = network.get_lane(index)
    gap = lane.position(0.0, 0.0) - end
    distance = float(np.hypot(*gap))
    if abs(wrap_angle(lane.heading_at(0.0) - heading)) > np.pi / 2:
        return False
    if distance <= JOIN:
        return True
    return distance <= BRIDGE and abs(wrap_angle(float(np.arctan2(gap[1], gap[0])) - heading)) < np.pi / 4


def needed_lane(network: RoadNetwork, route: list, lane: int) -> tuple | None:
    """The lane the EV, in lane number ``lane`` of its road, must be in to go on along ``route`` (lane indices,
    highway-env's; the roads' lanes parallel, numbered alike): on the first road of the route whose next road goes
    on (:func:`joins`) from some of its lanes only and not from lane ``lane``, the nearest lane that does (exit-v0:
    the exit lane ``("1", "2", 6)``); None where the EV's lane goes on all along."""
    for (a, b, _), (c, d, k) in zip(route, route[1:]):
        nexts = [(c, d, j) for j in range(len(network.graph[c][d]))] if k is None else [(c, d, k)]
        joined = [i for i, own in enumerate(network.graph[a][b]) if any(goes_on_from(network, n, own) for n in nexts)]
        if joined and lane not in joined:
            return (a, b, min(joined, key=lambda i: abs(i - lane)))
    return None


def goes_on_beside(network: RoadNetwork, index: tuple, following: tuple) -> bool:
    """Whether ``following`` (``network.next_lane`` after lane ``index``, along a route) is another lane than
    ``index`` that does not go on from ``index``'s end (:func:`joins`): the route's next road leaves from a lane
    beside (exit-v0's exit, 24 m to the side), which highway-env's next_lane reaches by a chord."""
    return following != index and not goes_on_from(network, following, network.get_lane(index))


def goes_on_from(network: RoadNetwork, index: tuple, lane) -> bool:
    """Whether lane ``index`` goes on from the end of ``lane`` (a highway-env lane): :func:`joins` at its end."""
    return joins(network, index, lane.position(lane.length, 0.0), lane.heading_at(lane.length))


def _edges(network, xy: np.ndarray, heading: np.ndarray, index, offset: float = 0.0) -> tuple[float, float]:
    """Left and right edge offsets [m] at the route point ``xy (2,)`` of heading ``heading`` on lane ``index``,
    ``offset`` m right of its centre."""
    beside = _beside(network, index)
    normal = np.array([-np.sin(heading), np.cos(heading)])
    own = network.get_lane(index)
    s_own, _ = coordinates(own, xy)
    left, right = -own.width_at(s_own) / 2.0 - offset, own.width_at(s_own) / 2.0 - offset
    for lane in beside:
        s, _ = coordinates(lane, xy)
        if not -1.0 <= s <= lane.length + 1.0:
            continue
        lat = float(np.dot(lane.position(s, 0.0) - xy, normal))
        turn = abs(wrap_angle(lane.heading_at(s) - heading))
        if abs(lat) > NEAR or np.pi / 3 < turn < 2 * np.pi / 3:  # beside the route: along it, or against it
            continue
        half = lane.width_at(s) / 2.0
        left, right = min(left, lat - half), max(right, lat + half)
    return left, right


def off_lanes(network: RoadNetwork, points: np.ndarray, margin: float, besides=None) -> bool:
    """Whether a point of ``points (P, 2)`` lies on no lane of the network, a point within ``margin`` m of a lane
    counting as on it: the drivable area, as the union of highway-env's lanes. Two uses (the adapter's offroad):
    - the body corners, where the route's edges put one outside (``edge_distance < 0``): those edges are the
      planner's view of the road ahead, and at a junction (a roundabout's entry, an exit) the EV crosses lanes
      beside its route that they leave out. highway-env's lanes leave slivers uncovered where they meet at an
      angle (a roundabout's entry and ring): the adapter's ``JUNCTION_MARGIN``;
    - the centre, where highway-env's ``on_road`` is false: it asks the EV's own lane only, so a centre in the
      seam between two lanes of one road would end the episode on a road drawn as one. The other lanes only
      (``besides``, the EV's own, left out), within the adapter's ``SEAM_MARGIN``: where lanes meet without a
      seam, as on every straight road, the rule is highway-env's exactly."""
    lanes = [lane for lane in network.lanes_list() if lane is not besides]
    return any(not any(lane.on_lane(point, *coordinates(lane, point), margin=margin) for lane in lanes)
               for point in points)


def on_lanes_of(network: RoadNetwork) -> Callable[[np.ndarray], bool]:
    """Whether every point of ``points (P, 2)`` lies on a lane of ``network``, with no margin, as a function of the
    points: the road-edge guard's drivable area (``Scene.on_lanes``), the lanes beside a junction included, which the
    route's edges leave out. No margin, unlike :func:`off_lanes`' ``JUNCTION_MARGIN``: the guard brakes before the
    env's test would end the episode, not after."""
    return partial(_on_lanes, network)


def _on_lanes(network: RoadNetwork, points: np.ndarray) -> bool:
    return not off_lanes(network, np.asarray(points, float), 0.0)


def coordinates(lane, xy: np.ndarray) -> tuple[float, float]:
    """``lane.local_coordinates(xy)``, mended for a circular lane of more than half a turn: highway-env wraps the
    phase to within pi of the start, so the last metres of such an arc (racetrack-v0's road d-e, 3.16 rad) read as
    lying a whole lap before its start. The branch nearest the lane's extent is taken."""
    s, lat = lane.local_coordinates(xy)
    if isinstance(lane, CircularLane) and lane.length > np.pi * lane.radius:
        lap = 2 * np.pi * lane.radius
        s = min((s - lap, s, s + lap), key=lambda c: max(-c, c - lane.length, 0.0))
    return float(s), float(lat)



def _beside(network, index) -> list:
    """The lanes whose sides may bound the route on lane ``index``'s road (:func:`_edges`), kept on the network
    (a road's lanes do not change within an episode, and a reset builds a new network)."""
    cache = network.__dict__.setdefault("_bimp_beside", {})
    if index not in cache:
        _from, _to, _ = index
        graph = network.graph
        beside = list(graph[_from][_to])
        if _to in graph and _from in graph[_to]:
            beside += list(graph[_to][_from])
        # Junctions: the roads merging into the route road's end (a roundabout's entry beside its ring, merge-v0's
        # ramp) and diverging from its start (an intersection's other turns) are drivable where they run beside it.
        beside += [lane for node, roads in graph.items() if node != _from and _to in roads for lane in roads[_to]]
        beside += [lane for node, lanes_ in graph[_from].items() if node != _to for lane in lanes_]
        cache[index] = beside
    return cache[index]


def build_route(network, index, position, route=None, behind: float = BEHIND, ahead: float = AHEAD,
                spacing: float = SPACING) -> tuple[Route, list]:
    """The :class:`Route` along lane ``index`` through ``position (2,)``: from ``behind`` m before it (at most to
    the lane's start) to ``ahead`` m after it along ``route``, padded straight to ``ahead`` where the network ends.
    Also the lane index of every point (the padding repeats the last). Headings are unwrapped along the route."""
    lane = network.get_lane(index)
    s0, _ = coordinates(lane, np.asarray(position, float))
    start = float(np.clip(s0 - behind, 0.0, max(lane.length - spacing, 0.0)))
    xy, heading, lanes, bridges = lane_walk(network, index, start, ahead + (s0 - start), route_from(route, index),
                                            spacing)
    xy, heading, lanes, offset = smooth_bridges(network, xy, np.unwrap(heading), lanes, bridges, spacing)
    keep = _spaced(xy, spacing / 2)  # a lane's end sample and joins give points closer than that: no stub segments
    xy, heading, lanes = xy[keep], np.unwrap(heading[keep]), [lane_ for lane_, k in zip(lanes, keep) if k]
    offset = offset[keep]
    if len(xy) < 2:  # a lane shorter than a point's spacing at the network's end: one step along its heading
        xy = np.vstack([xy, xy[-1] + spacing * np.array([np.cos(heading[-1]), np.sin(heading[-1])])])
        heading, lanes, offset = np.append(heading, heading[-1]), lanes + lanes[-1:], np.append(offset, 0.0)
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    missing = (s0 - start) + ahead - s[-1]
    if missing > spacing:  # the network ended: straight on along the last heading
        extra = spacing * np.arange(1, int(np.ceil(missing / spacing)) + 1)
        direction = np.array([np.cos(heading[-1]), np.sin(heading[-1])])
        xy = np.vstack([xy, xy[-1] + extra[:, None] * direction])
        s = np.concatenate([s, s[-1] + extra])
        heading = np.concatenate([heading, np.full(len(extra), heading[-1])])
        lanes = lanes + [lanes[-1]] * len(extra)
        offset = np.concatenate([offset, np.zeros(len(extra))])
    measured = np.arange(0, len(xy), EDGE_EVERY)
    if measured[-1] != len(xy) - 1:
        measured = np.append(measured, len(xy) - 1)
    edges = np.array([_edges(network, xy[i], heading[i], lanes[i], offset[i]) for i in measured])
    left = np.interp(np.arange(len(xy)), measured, edges[:, 0])
    right = np.interp(np.arange(len(xy)), measured, edges[:, 1])
    curvature = np.gradient(heading, s)
    return Route(xy=xy, s=s, heading=heading, curvature=curvature, left=left, right=right), lanes


def route_from(route, index):
    """The part of ``route`` (a list of lane indices) from the road of lane ``index`` on: ``next_lane`` follows a
    route only from its first road, and the EV's route starts where its episode did. None where the route does not
    pass that road (the lane graph's own choice then)."""
    if not route:
        return None
    for k, step in enumerate(route):
        if tuple(step[:2]) == tuple(index[:2]):
            return list(route[k:])
    return None


SLACK = 100.0  # m: a kept route reaches this far past AHEAD, so it serves about SLACK m of driving between builds
SELF, LOOP = 2.0, 20.0  # m: a route within SELF m of itself LOOP m further along has come round (_once_round)


class RouteCache:
    """The EV's :func:`build_route`, built ``slack`` m longer than ``ahead`` and kept while it serves: rebuilt only
    when the EV's lane sequence changes (its lane is not one the kept route walks, or the planned route from its
    road on differs), when less than ``ahead`` m of the kept route lies ahead of the EV or the EV is behind where it
    was built, and on a new network (a reset). A build costs milliseconds, the check microseconds."""

    def __init__(self, behind: float = BEHIND, ahead: float = AHEAD, slack: float = SLACK, spacing: float = SPACING):
        if not (behind >= 0 and ahead > 0 and slack >= 0 and spacing > 0):
            raise ValueError(f"a route cache needs behind >= 0, ahead > 0, slack >= 0, spacing > 0 (m), got "
                             f"{behind}, {ahead}, {slack}, {spacing}")
        self.behind, self.ahead, self.slack, self.spacing = behind, ahead, slack, spacing
        self.builds = 0
        self._network = self._route = self._plan = None
        self._points: dict[tuple, np.ndarray] = {}
        self._s_built = 0.0

    def get(self, network: RoadNetwork, index: tuple, position: np.ndarray,
            route: list | None = None) -> tuple[Route, int]:
        """The route along lane ``index`` through ``position (2,)`` (:func:`build_route`'s arguments) and the index
        of its point nearest to ``position`` among lane ``index``'s points."""
        position = np.asarray(position, float)
        at = self._serves(network, index, position, route)
        if at is None:
            self._route, lanes = _once_round(*build_route(network, index, position, route, self.behind,
                                                          self.ahead + self.slack, self.spacing))
            if self._route.s[-1] - self._route.s[0] < self.behind + self.ahead:  # a loop shorter than the slack
                self._route, lanes = build_route(network, index, position, route, self.behind, self.ahead,
                                                 self.spacing)
            self._network, self._plan, self.builds = network, list(route) if route else None, self.builds + 1
            self._points = {}
            for k, lane in enumerate(lanes):
                self._points.setdefault(lane, []).append(k)
            self._points = {lane: np.array(ks) for lane, ks in self._points.items()}
            at = self._nearest(index, position)
            self._s_built = float(self._route.s[at])
        return self._route, at

    def _nearest(self, index, position: np.ndarray) -> int:
        points = self._points[index]
        return int(points[np.argmin(((self._route.xy[points] - position) ** 2).sum(-1))])

    def _serves(self, network, index, position: np.ndarray, route) -> int | None:
        """The EV's point on the kept route where that route still serves, else None."""
        if (self._route is None or network is not self._network or index not in self._points
                or route_from(self._plan, index) != route_from(route, index)):
            return None
        at = self._nearest(index, position)
        s = self._route.s
        if s[at] < self._s_built - self.spacing or s[-1] - s[at] < self.ahead:
            return None
        return at


def _once_round(route: Route, lanes: list) -> tuple[Route, list]:
    """``route`` up to where it comes back onto itself (a loop: racetrack-v0's inner lane is about 345 m round,
    less than a kept route's 380): a point more than ``LOOP`` m along it within ``SELF`` m of an earlier one. Past
    there it would lie on itself, and a point on it would project on either pass."""
    xy, s = route.xy, route.s
    close = (np.hypot(*(xy[:, None, :] - xy[None, :, :]).T) < SELF) & (s[:, None] - s[None, :] > LOOP)
    back = np.flatnonzero(close.any(axis=1))
    if not len(back):
        return route, lanes
    k = int(back[0])
    return Route(xy=xy[:k], s=s[:k], heading=route.heading[:k], curvature=route.curvature[:k],
                 left=route.left[:k], right=route.right[:k]), lanes[:k]


def steering_needed(lane, length: float) -> float:
    """The steering [rad] highway-env's bicycle (wheelbase ``length``) needs to hold ``lane``'s tightest curve:
    ``tan(delta) = 2 tan(asin(length / (2 R)))`` (its slip angle is ``atan(tan(delta) / 2)``); 0 for a straight
    lane, ``inf`` for a curve tighter than ``length / 2``. Circular lanes by their radius, sine lanes by their peak
    curvature ``amplitude * pulsation^2``."""
    if hasattr(lane, "radius"):
        curvature = 1.0 / float(lane.radius)
    elif hasattr(lane, "amplitude") and hasattr(lane, "pulsation"):
        curvature = abs(float(lane.amplitude)) * float(lane.pulsation) ** 2
    else:
        return 0.0
    half_chord = length * curvature / 2
    return float(np.arctan(2 * np.tan(np.arcsin(half_chord)))) if half_chord < 1 else float("inf")


def check_steering_reach(network: RoadNetwork, route, steer_range: tuple[float, float], length: float,
                         name: str) -> None:
    """``ValueError`` naming the curve and the range when a lane of ``route`` (lane indices; an index without a lane
    id is each lane of its road; no route at all, a loop such as the racetrack: every lane of the network) needs more
    steering (:func:`steering_needed`) than the actuator's ``steer_range`` [rad] reaches: no policy could hold it."""
    reach = min(-float(steer_range[0]), float(steer_range[1]))
    roads = [(a, b, i) for a, b, i in route] if route else \
        [(a, b, None) for a, ends in network.graph.items() for b in ends]
    indices = [(a, b, i) for a, b, lane_id in roads
               for i in ([lane_id] if lane_id is not None else range(len(network.graph[a][b])))]
    for index in indices:
        lane = network.get_lane(index)
        needed = steering_needed(lane, length)
        if needed > reach:
            curve = f"radius {float(lane.radius):g} m" if hasattr(lane, "radius") else "peak curvature"
            raise ValueError(f"{name}: the route's curve on lane {tuple(index)} ({curve}) needs {needed:.3f} rad of "
                             f"steering, past the actuator's steering range ±{reach:g} rad")
