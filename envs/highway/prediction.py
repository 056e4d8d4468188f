"""Other vehicles' paths along their lanes: what the planners predict on a junction road.

The planners' own prediction (:func:`bimp.planners.problem.predict_obstacles`) moves each OV along its heading in the
frame of the EV's route: right where the OV's lane runs beside the route, wrong where it does not. At roundabout-v0's
entry the ring's vehicles head 0.6 rad off the entry road's heading, so the ring's inner lane was predicted to sweep
11 m across the EV's lane in 2 s, and the plan swerved off the road to let it (EnKTS and EnKS on results seeds 1075 and
1096). highway-env knows each vehicle's lane and route: here each OV drives on along them (``lanes.lane_walk``), at
its constant acceleration (the planners' rule), keeping its heading relative to its lane (a lane change drifts on as
before). The adapter publishes the paths in the scene (``Scene.ov_paths``) on the junction roads (``Profile.junction``).
"""

from __future__ import annotations

import numpy as np

from bimp.envs.highway.lanes import coordinates, lane_walk, route_from
from bimp.envs.road import wrap_angle
from bimp.envs.scene import travel

PATH_STEPS = 40  # steps of 0.1 s: 4 s, twice the planners' default horizon (a planner extends a path past its end)


def lane_path(network, vehicle, accel: float, t: np.ndarray) -> np.ndarray:
    """``(T, 3)`` ``[x, y, heading]`` of ``vehicle`` at times ``t (T,)``: along its lane and route (the lane graph's
    own choice past the route), its lateral offset changing by its heading relative to the lane; straight on past
    the network's end. A vehicle on no lane (a road object) stays where it is."""
    index = getattr(vehicle, "lane_index", None)
    position, heading = np.asarray(vehicle.position, float), float(vehicle.heading)
    if index is None or index[0] is None:
        return np.tile([*position, heading], (len(t), 1))
    lane = network.get_lane(index)
    # The foot of the perpendicular from the vehicle to the lane's centre and the offset along that normal: a
    # SineLane's own coordinates are across its straight base, and the path started 0.6 m off the vehicle at
    # roundabout-v0's entries. Refined from the lane's own coordinate in three steps: exact at once on straight
    # lanes and circles; on a sine lane, whose coordinate runs along its base (each step overshoots by the slope's
    # 1 / cos), within 1e-6 m of the foot at roundabout-v0's entries (tested).
    s0 = float(np.clip(coordinates(lane, position)[0], 0.0, lane.length))
    for _ in range(3):
        h0 = lane.heading_at(s0)
        s0 = float(np.clip(s0 + np.dot(position - lane.position(s0, 0.0), [np.cos(h0), np.sin(h0)]), 0.0,
                           lane.length))
    h0 = lane.heading_at(s0)
    l0 = float(np.dot(position - lane.position(s0, 0.0), [-np.sin(h0), np.cos(h0)]))
    dh = wrap_angle(heading - h0)
    d = travel(float(vehicle.speed), accel, t)
    along, lateral = np.cos(dh) * d, l0 + np.sin(dh) * d
    route = getattr(vehicle, "route", None)
    # highway-env pops a route's road half a car before the lane's end (``follow_road``: the target lane is then
    # the next road's, the lane still this one); the rest of the route goes on from this lane's end.
    plan = route_from(route, index) or (list(route) if route and route[0][0] == index[1] else None)
    xy, headings, _, _ = lane_walk(network, index, s0, float(along.max()) + 1.0, plan)
    headings = np.unwrap(headings)
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    past = np.maximum(along - arc[-1], 0.0)  # straight on along the last heading where the walk ended
    h = np.interp(along, arc, headings)
    centre = np.stack([np.interp(along, arc, xy[:, 0]), np.interp(along, arc, xy[:, 1])], axis=1)
    centre += past[:, None] * np.stack([np.cos(headings[-1]), np.sin(headings[-1])])
    # highway-env's lateral offset is to the right of travel: (-sin h, cos h) in its frame (y down the screen)
    normal = np.stack([-np.sin(h), np.cos(h)], axis=1)
    return np.column_stack([centre + lateral[:, None] * normal, h + dh])


def lane_paths(network, vehicles: list, accels: list[float], n: int, dt: float,
               steps: int = PATH_STEPS) -> np.ndarray:
    """``(n, steps + 1, 3)``: :func:`lane_path` of the first ``n`` of ``vehicles`` (the observation's slots, in its
    order) at ``0, dt, ..., steps dt``; zeros for an empty slot (the observation marks it absent)."""
    t = dt * np.arange(steps + 1)
    paths = np.zeros((n, steps + 1, 3))
    for k, (vehicle, accel) in enumerate(zip(vehicles[:n], accels)):
        paths[k] = lane_path(network, vehicle, accel, t)
    return paths


__all__ = ["PATH_STEPS", "lane_path", "lane_paths"]
