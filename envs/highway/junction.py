"""Yielding at junctions by gap acceptance: the behaviour layer's rule at a roundabout's entry and an intersection's
crossing, where highway-env's own driver has none (IDM follows the vehicle ahead in its lane only, and
intersection-v0's ``RegulatedRoad`` stops its traffic for priority but never the EV).

The conflict is found along the lane graph, not along straight headings. The EV's path is its route's lane centres
ahead (highway-env's ``RoadNetwork.position_heading_along_route``, every :data:`PATH_STEP` m); every other vehicle
is predicted along its own route at constant speed, as highway-env's ``predict_trajectory_constant_speed`` predicts
it for its own regulation (a vehicle without a route: along its heading). The other vehicle *occupies* the EV's path
at the times its predicted centre lies within :data:`PATH_HALF_WIDTH` of it, at the path's nearest arc length.

Gap acceptance: the EV goes if, driving on as IDM accelerates it on a free road, it passes every such occupation at
least :data:`MARGIN_TIME` s after the other vehicle or :data:`MARGIN_FIRST` s before it (and :data:`MARGIN_LENGTH` m
apart); otherwise it yields: IDM brakes towards a stopped vehicle standing at the first conflicting arc length, or
at the stop line where that lies beyond it (:class:`Yielding`). It commits to a conflict once it can no longer stop
short of it comfortably (the stop would need more than :data:`COMMIT_DECEL`) or is already in it, and to the whole
junction once it has entered it. Vehicles in the EV's own lane, or on its path heading along it, are left to IDM (a
leader, a follower)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from highway_env.road.regulation import RegulatedRoad

from bimp.envs.highway.lanes import coordinates

HORIZON = 6.0  # s: how far ahead arrival times are compared
TIME_STEP = 0.25  # s: of the other vehicles' predictions (highway-env's regulation uses 0.25 s)
PATH_STEP = 1.0  # m: between the EV's path points
PATH_HALF_WIDTH = 2.5  # m: a predicted centre this near the EV's path occupies it (a vehicle's width and 0.5 m)
MARGIN_TIME = 1.5  # s: the gap the EV keeps behind another vehicle at a conflict (the other passes first)
MARGIN_FIRST = 2.0  # s: ahead of one (the EV passes first): highway-env's IDM brakes for no vehicle on another lane
MARGIN_LENGTH = 6.0  # m: centre to centre, a vehicle's length and a metre
COMMIT_DECEL = 4.0  # m/s^2: beyond this braking to stop short of the conflict, the EV goes on
SEARCH_RADIUS = 80.0  # m: other vehicles farther from the EV are not considered
BEHIND = 30.0  # m: the EV's path reaches this far back, to know the vehicles that follow it


def resolved_route(vehicle) -> list:
    """``vehicle``'s route from its current lane (its lane where it has none) with every lane named: on a road the
    route names no lane of, the one starting nearest to the end of the lane before, as highway-env's ``next_lane``
    picks it. highway-env's own ``position_heading_along_route`` keeps the current lane's id there (on roundabout-v0
    the inner ring behind an entry that leads into the outer one; an IndexError where the next road has fewer
    lanes), and its driver pops the current lane from the route a little before the lane's end. The current lane
    is not put in front of a route whose first road starts where it starts: at a fork highway-env's nearest lane
    may be the other branch's (the route's own road then leads the way, or the vehicle is predicted the wrong way
    round)."""
    network = vehicle.road.network
    given = list(vehicle.route or [])
    if not given or given[0][0] != vehicle.lane_index[0]:
        given = [vehicle.lane_index, *given]
    route, end = [], None
    for a, b, k in given:
        lanes = network.graph[a][b]
        if k is None:
            k = (min(vehicle.lane_index[2], len(lanes) - 1) if end is None else
                 int(np.argmin([np.linalg.norm(lane.position(0.0, 0.0) - end) for lane in lanes])))
        end = lanes[k].position(lanes[k].length, 0.0)
        route.append((a, b, k))
    return route


def along_route(vehicle, distances: np.ndarray) -> np.ndarray:
    """Lane-centre points ``(T, 2)`` ``distances`` ``(T,)`` [m] ahead of ``vehicle``'s abreast position along its
    :func:`resolved_route`, as highway-env's ``predict_trajectory_constant_speed`` places them."""
    network, route = vehicle.road.network, resolved_route(vehicle)
    s0 = coordinates(network.get_lane(route[0]), vehicle.position)[0]
    return np.array([network.position_heading_along_route(route, s0 + d, 0.0, vehicle.lane_index)[0]
                     for d in distances], float).reshape(-1, 2)


def predicted_positions(vehicle, times: np.ndarray) -> np.ndarray:
    """``vehicle``'s centre ``(T, 2)`` at ``times`` ``(T,)`` [s]: along its route at constant speed (highway-env's
    own prediction, :func:`along_route`) where it follows lanes, else straight along its heading."""
    if hasattr(vehicle, "route") and getattr(vehicle, "lane", None) is not None:
        return along_route(vehicle, vehicle.speed * times)
    direction = np.array([np.cos(vehicle.heading), np.sin(vehicle.heading)])
    return np.asarray(vehicle.position, float) + vehicle.speed * times[:, None] * direction


def go_distance(speed: float, target: float, accel: float, times: np.ndarray) -> np.ndarray:
    """Arc length [m] ``(T,)`` covered by ``times`` starting at ``speed`` [m/s] and accelerating at ``accel``
    up to ``target``."""
    t_top = max(target - speed, 0.0) / accel
    t = np.minimum(times, t_top)
    return speed * t + 0.5 * accel * t ** 2 + max(target, speed) * np.maximum(times - t_top, 0.0)


class Yielding:
    """The EV's gap acceptance over one episode (module docstring). Before its junction the EV yields to every
    vehicle, or on highway-env's ``RegulatedRoad`` (intersection-v0) to those its rule makes the EV yield to (on a lane
    of higher ``priority``; at equal priority, when the EV is the one behind): the road stops the others for the EV.
    It stops at the latest at the *stop line*, the start of the first lane of its route that starts at a node where
    roads join or fork (a roundabout's ring at its entry, an intersection's turning lanes). It has *entered* once it
    drives on such a lane without yielding; from there on it yields to nobody: it has the right of way as the ring's
    traffic has, and stopping inside a crossing blocks it. Reaching the stop line enters it too: a conflict first seen
    there would place the stop beyond the line, inside the junction."""

    def __init__(self) -> None:
        self.entered = False

    def stop_distance(self, driver, others) -> float | None:
        """The arc length [m] along ``driver``'s path (the EV's shadow, synced to it) of the first conflict it yields
        at, None where it goes: IDM stops it about ``DISTANCE_WANTED`` short of that (at the stop line, where the
        conflict lies beyond it). ``others``: the other vehicles of the road."""
        if self.entered:
            return None
        network = driver.road.network
        if isinstance(driver.road, RegulatedRoad):  # its traffic yields by its rule: the EV yields where it says
            rivals = [v for v in others if hasattr(v, "lane") and RegulatedRoad.respect_priorities(driver, v) is driver]
        else:
            rivals = list(others)
        stop = stop_distance(driver, rivals) if rivals else None
        if stop is None:
            self.entered = junction(network, driver.lane_index[0])
            return None
        line = stop_line(driver)
        if line is not None and line <= 0.0:  # at the line: a stop now would be inside the junction
            self.entered = True
            return None
        return stop if line is None else min(stop, line + driver.DISTANCE_WANTED - driver.LENGTH / 2)


def junction(network, node) -> bool:
    """Whether roads from more than one node lead into ``node`` or from it to more than one."""
    return sum(node in ends for ends in network.graph.values()) > 1 or len(network.graph.get(node, {})) > 1


def stop_line(vehicle) -> float | None:
    """The distance [m] from ``vehicle``'s abreast position to the start of the first lane ahead on its route that
    starts at a :func:`junction` (0 on such a lane), None where there is none."""
    network = vehicle.road.network
    route = resolved_route(vehicle)
    ahead = -coordinates(network.get_lane(route[0]), vehicle.position)[0]
    for index in route:
        if junction(network, index[0]):
            return max(ahead, 0.0)
        ahead += network.get_lane(index).length
    return None


def stop_distance(driver, others) -> float | None:
    """The arc length [m] along ``driver``'s path (the EV's shadow, synced to it) of the first conflict with one of
    ``others`` that it can still stop short of comfortably, None where there is none."""
    times = np.arange(TIME_STEP, HORIZON + TIME_STEP / 2, TIME_STEP)
    target = float(driver.target_speed)
    accel = float(driver.COMFORT_ACC_MAX)
    speed = max(float(driver.speed), 0.0)
    early = go_distance(speed, target, accel, np.maximum(times - MARGIN_FIRST, 0.0))
    late = go_distance(speed, target, accel, times + MARGIN_TIME)
    arc = np.arange(-BEHIND, late[-1] + MARGIN_LENGTH + PATH_STEP, PATH_STEP)
    path = along_route(driver, arc)
    here = np.asarray(driver.position, float)
    stop = None
    for other in others:
        if other is driver or np.linalg.norm(np.asarray(other.position) - here) > SEARCH_RADIUS:
            continue
        if getattr(other, "lane_index", None) == driver.lane_index or _along(other, path):
            continue  # a leader or a follower: IDM's
        future = predicted_positions(other, times)
        gaps = np.linalg.norm(future[:, None, :] - path[None, :, :], axis=-1)  # (T, M)
        nearest = gaps.argmin(axis=1)
        s_other = arc[nearest]
        on_path = (gaps[np.arange(len(times)), nearest] < PATH_HALF_WIDTH) & (s_other >= 0.0)
        clash = on_path & (s_other > early - MARGIN_LENGTH) & (s_other < late + MARGIN_LENGTH)
        if not clash.any():
            continue
        first = float(s_other[clash].min())
        room = first - MARGIN_LENGTH
        if room <= 0.0 or speed ** 2 / (2 * room) > COMMIT_DECEL:
            continue  # committed: in this conflict, or too near to stop short of it
        stop = first if stop is None else min(stop, first)
    return stop


def _along(vehicle, path: np.ndarray) -> bool:
    """Whether ``vehicle`` is on the EV's path ``(M, 2)`` (from :data:`BEHIND` m back) now, heading along it: one the
    EV follows or that follows it."""
    gaps = np.linalg.norm(path - np.asarray(vehicle.position, float), axis=1)
    k = int(gaps.argmin())
    if gaps[k] >= PATH_HALF_WIDTH:
        return False
    tangent = path[min(k + 1, len(path) - 1)] - path[max(k - 1, 0)]
    return bool(np.dot(tangent, [np.cos(vehicle.heading), np.sin(vehicle.heading)]) > 0.5 * np.linalg.norm(tangent))


def yield_acceleration(driver, distance: float) -> float:
    """IDM's acceleration [m/s^2] of ``driver`` behind a stopped vehicle ``distance`` m ahead, centre to centre:
    highway-env's ``IDMVehicle.acceleration`` on a free road less its interaction term, with its ``desired_gap`` to a
    vehicle at 0 m/s (highway-env measures the distance along the EV's lane, where the stop may lie on the next)."""
    gap = driver.desired_gap(driver, SimpleNamespace(speed=0.0), projected=False)
    return float(driver.acceleration(driver) - driver.COMFORT_ACC_MAX * (gap / max(distance, 1e-6)) ** 2)
