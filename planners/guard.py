"""The road-edge guard: braking in lane where the smoothed plan leaves the road.

The planners' road edge is a soft barrier (paper eq. 3 as one more virtual observation). Where a cut-in leaves no room
in the lane, the collision barrier can outweigh it, and the smoothed plan swerves off the road. A controller needs a
hard limit there, so the guard checks the plan every step.

1. The smoothed plan's states ``x_1 .. x_H`` are rolled out on the planner's own model.
2. The guard acts when a body corner of any of them lies past the drivable area's edge
   (:meth:`bimp.envs.scene.Scene.edge_distance` < 0), further out than the EV is now (an EV already over the edge
   may come back), and on no lane where the scene knows its lanes (``Scene.on_lanes``: at a roundabout's entry the
   route's edges are the entry lane's, and the ring beside it is drivable too).
3. Then the applied control is replaced by braking in lane (:func:`brake_in_lane`): the planning bound's full
   braking, with steering that holds the road's heading.

The next plan starts from the planner's own warm start, so the guard overrides one control, not the planner's
search. numpy, one EV per call; the planners call it per row.
"""

from __future__ import annotations

import numpy as np

from bimp.envs.road import body_corners, wrap_angle
from bimp.envs.scene import Scene

HEADING_TIME = 0.5  # [s] the brake-in-lane steering takes out a heading error over about this long


def leaves_road(scene: Scene, x0: np.ndarray, states: np.ndarray) -> bool:
    """Whether the planned ``states (H, >=3)`` put a body corner past the road's edge, further out than the EV at
    ``x0 (>=3,)`` is (:meth:`Scene.edge_distance`: > 0 inside), and, where the scene knows its lanes
    (``Scene.on_lanes``), on no lane: at a junction the route's edges leave out the lanes beside it."""
    states = np.asarray(states, float)
    margins = scene.edge_distance(np.vstack([np.asarray(x0, float)[:4], states[:, :4]]))
    out = states[margins[1:] < min(margins[0], 0.0)]  # one projection of the EV's and the plan's corners
    if scene.on_lanes is None or not len(out):
        return bool(len(out))
    corners = body_corners(out[:, :2], out[:, 2], scene.vehicle_length, scene.vehicle_width)
    return not scene.on_lanes(corners.reshape(-1, 2))


def brake_in_lane(scene: Scene, x0: np.ndarray) -> np.ndarray:
    """The physical input ``[a m/s^2, delta rad] (2,)`` that brakes in lane from the EV state ``x0 [x, y, heading,
    speed]``: the planning bound's full braking, and the steering of highway-env's bicycle that turns with the road
    (its curvature's feed-forward, ``atan(L kappa)``) and takes out the heading error relative to the road over
    :data:`HEADING_TIME`, clipped to the planning bound."""
    x0 = np.asarray(x0, float)
    p = scene.road.project(x0[:2])
    error = float(wrap_angle(x0[2] - float(p.heading)))
    speed = max(float(x0[3]), 1.0)  # slow: steer as at 1 m/s, not by a rate that grows without bound
    yaw_rate = speed * float(p.curvature) - error / HEADING_TIME
    steer = np.arctan(scene.vehicle_length * yaw_rate / speed)
    bound = scene.bounds.steer
    return np.array([scene.bounds.accel[0], float(np.clip(steer, -bound, bound))])


def guarded(scene: Scene, x0: np.ndarray, states: np.ndarray, action: np.ndarray) -> tuple[np.ndarray, bool]:
    """``(action, acted)``: the normalized ``action (2,)`` the plan chose, or braking in lane (normalized) where the
    plan's ``states (H, >=3)`` leave the road (:func:`leaves_road`)."""
    if not leaves_road(scene, x0, states):
        return np.asarray(action, np.float32), False
    return scene.to_normalized(brake_in_lane(scene, x0)).astype(np.float32), True


__all__ = ["HEADING_TIME", "brake_in_lane", "guarded", "leaves_road"]
