"""The virtual system of the paper (eq. 7-8): what a plan is measured against.

Per horizon step ``t`` a particle carries ``xb_t = [x_t (4), u_t (2), du_t (2)]``. Its virtual measurement
``y_t = [r_t (3), s_t (2), z_t (7)]`` is observed as all zeros:

- reference state ``r``, in road coordinates: lateral offset to the reference lane [m], heading relative to
  the road [rad], speed minus the reference speed [m/s]. (Tracking a world position would pull the EV to a
  point; the longitudinal position is left free.)
- reference input ``s``: acceleration minus the reference speed's rate [m/s^2], steering minus the road
  curvature's feedforward angle [rad].
- barriers ``z = psi(phi)``, one per constraint family (a vector, not a sum, so the ensemble regression can
  tell which constraint a particle breaks): each OV, the road edges, the acceleration bound, the steering
  bound, the acceleration rate, the steering rate. ``psi`` is a softplus hinge of ``phi / width`` (finite,
  smooth, ~0 when satisfied), so a constraint reads like a measurement of 0 with noise ``sigma_barrier``:
  the tightness of the barrier.

The collision family inflates the footprint by a time headway: ahead of an OV the EV needs
``d_min + headway * v`` of road, so the danger enters the horizon while braking still suffices.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from configs import ConfigError, check_fields
from envs.scene import Scene

N_TRACK = 5  # r (3) + s (2)
BARRIERS = ("ov (one per OV)", "road_edge", "accel", "steer", "accel_rate", "steer_rate",
            "first accel", "first steer", "first accel_rate", "first steer_rate")


@dataclass(frozen=True)
class BarrierShape:
    """Margins and widths of the barriers.

    headway [s]: time gap added to ``d_min`` behind (or ahead of) an OV; brake_decel [m/s^2]: deceleration
    the braking room behind an OV is reckoned with; lateral_clearance [m]: least
    side gap between footprints; edge_margin [m]: least corner distance to the edge the planner aims for;
    bound_margin: fraction by which the planner tightens the input and rate bounds (the barriers are soft:
    the ensemble mean settles a little past where they start to read);
    widths: the constraint violation that makes a barrier read 1, per family, in its own units
    [share of the keep-out ellipse, m, m/s^2, rad, m/s^2, rad]; sharpness: softplus sharpness in those normalized units.
    Checked by :func:`configs.check_fields`, then headway, lateral_clearance >= 0, brake_decel, widths,
    sharpness > 0, bound_margin in [0, 1): a bad value raises :class:`configs.ConfigError` naming it.
    """

    headway: float = 0.6
    brake_decel: float = 6.0
    lateral_clearance: float = 1.0
    edge_margin: float = 0.3
    widths: tuple[float, float, float, float, float, float] = (0.1, 0.5, 1.0, 0.01, 0.5, 0.002)
    sharpness: float = 8.0
    bound_margin: float = 0.05

    def __post_init__(self) -> None:
        check_fields(self)
        for key in ("headway", "lateral_clearance"):
            if getattr(self, key) < 0:
                raise ConfigError(key, ">= 0", getattr(self, key))
        for key in ("brake_decel", "sharpness"):
            if not getattr(self, key) > 0:
                raise ConfigError(key, "> 0", getattr(self, key))
        if min(self.widths) <= 0:
            raise ConfigError("widths", "a list of 6 numbers > 0", self.widths)
        if not 0 <= self.bound_margin < 1:
            raise ConfigError("bound_margin", "in [0, 1)", self.bound_margin)


def predict_obstacles(scene: Scene, ovs: np.ndarray, horizon: int) -> tuple[np.ndarray, ...]:
    """Constant-acceleration prediction of the OVs along the road, speed never below 0.

    ovs: observation rows ``(K, 6)`` ``[present, x, y, heading, speed, accel]``.
    Returns ``s, l, v, a`` of shapes ``(horizon + 1, K)`` and ``present`` (bool ``(K,)``); index 0 = now.
    """
    s0, l0 = scene.road.to_frenet(ovs[:, 1:3])
    v0, a = ovs[:, 4], ovs[:, 5]
    t = np.arange(horizon + 1)[:, None] * scene.dt
    t_stop = np.where(a < 0, v0 / np.maximum(-a, 1e-9), np.inf)
    tc = np.minimum(t, t_stop)
    s = s0 + v0 * tc + 0.5 * a * tc**2
    v = np.maximum(v0 + a * t, 0.0)
    return s, np.broadcast_to(l0, s.shape), v, np.where(t < t_stop, a, 0.0), ovs[:, 0] > 0


def reference_profile(scene: Scene, ref: np.ndarray, horizon: int) -> tuple[np.ndarray, np.ndarray]:
    """Reference speed and its rate ``(horizon + 1,)`` each, extrapolating ``[v_ref, a_ref, l_ref]`` linearly,
    never below 0."""
    t = np.arange(horizon + 1) * scene.dt
    v = np.maximum(ref[0] + ref[1] * t, 0.0)
    return v, np.where(v > 0.0, ref[1], 0.0)


def _hinge(phi: np.ndarray, sharpness: float) -> np.ndarray:
    return np.logaddexp(0.0, sharpness * phi) / sharpness


def n_measurements(n_obstacles: int) -> int:
    """Size m of the virtual measurement: tracking (5), one barrier per OV, five more, four on the first control."""
    return N_TRACK + n_obstacles + 5 + 4


def measure(scene: Scene, shape: BarrierShape, x: np.ndarray, u: np.ndarray, du: np.ndarray, u0: np.ndarray,
            u_prev: np.ndarray, ref_lane: float, v_ref: float, a_ref: float,
            obstacles: tuple[np.ndarray, ...]) -> np.ndarray:
    """``h(xb)`` of eq. 8 without noise: ``(N, n_measurements(K))`` for states ``x (N, 4)``, inputs ``u (N, 2)``,
    increments ``du (N, 2)``; ``obstacles``: one horizon step of :func:`predict_obstacles` as ``(s, l, v, a)``, each
    ``(K,)``, and ``present (K,)``. Observed value: zeros.

    The smoothing pass keeps revising the first control ``u0 (N, 2)`` (the one applied) long after its own
    step, so its input and rate barriers (against ``u_prev (2,)``, the input applied last) are observed at
    every step, not only at step 0.
    """
    road, b = scene.road, scene.bounds
    s, lat = road.to_frenet(x[:, :2])
    dpsi = x[:, 2] - road.heading_at(s)
    v = x[:, 3]
    half_l, half_w = scene.vehicle_length / 2, scene.vehicle_width / 2
    feedforward = np.arctan(scene.vehicle_length * road.curvature_at(s))
    out = np.empty((x.shape[0], n_measurements(len(obstacles[0]))))
    out[:, 0] = lat - ref_lane
    out[:, 1] = dpsi
    out[:, 2] = v - v_ref
    out[:, 3] = u[:, 0] - a_ref
    out[:, 4] = u[:, 1] - feedforward

    s_o, l_o, v_o, a_o, present = obstacles
    w = shape.widths
    # Keep-out box around each OV (centre to centre): half-sizes of a footprint plus the clearance,
    # longitudinally the time headway of whichever vehicle follows plus its braking room. The barrier is the
    # smaller *relative* penetration, so a vehicle deep in the same lane is pushed to brake, and only a
    # plan that has mostly left the OV's lane gets credit for the lateral escape (within the lane, swerving
    # buys nothing and only heads for the road edge).
    ds = s[:, None] - s_o
    behind = ds < 0
    v_follow = np.where(behind, v[:, None], v_o)
    v_lead = np.where(behind, v_o, v[:, None])
    # Braking room: to match a leader that holds speed, closing^2 / 2b; behind an OV predicted to brake to
    # a stop, the difference of the stopping distances (the danger the 2 s horizon alone would see too late).
    room = np.maximum(v_follow - v_lead, 0.0) ** 2 / (2 * shape.brake_decel)
    a_lead = np.where(behind, a_o, 0.0)
    stop = v_follow**2 / (2 * shape.brake_decel) - v_lead**2 / (2 * np.maximum(-a_lead, 1e-6))
    room = np.maximum(room, np.where(a_lead < -0.5, stop, 0.0))
    semi_s = scene.vehicle_length + b.d_min + shape.headway * v_follow + room
    semi_l = scene.vehicle_width + shape.lateral_clearance
    phi_ov = np.minimum(1.0 - np.abs(ds) / semi_s, 1.0 - np.abs(lat[:, None] - l_o) / semi_l)
    phi_ov = np.where(present, phi_ov / w[0], -1e3)
    extent = np.abs(lat) + half_l * np.abs(np.sin(dpsi)) + half_w * np.cos(dpsi)
    # Input bounds as |u - centre| <= half-range (acceleration) and |delta| <= bound, tightened by the margin;
    # rates as |du| <= bound. Written for both [a, delta] columns at once.
    keep = 1.0 - shape.bound_margin
    centre = keep * np.array([(b.accel[0] + b.accel[1]) / 2, 0.0])
    half = keep * np.array([(b.accel[1] - b.accel[0]) / 2, b.steer])
    rate = keep * np.array([b.accel_rate, b.steer_rate])
    w_input, w_rate = np.array(w[2:4]), np.array(w[4:6])
    k = phi_ov.shape[1]
    phi = np.empty((x.shape[0], k + 9))
    phi[:, :k] = phi_ov
    phi[:, k] = (extent - road.half_width + shape.edge_margin) / w[1]
    phi[:, k + 1:k + 3] = (np.abs(u - centre) - half) / w_input
    phi[:, k + 3:k + 5] = (np.abs(du) - rate) / w_rate
    phi[:, k + 5:k + 7] = (np.abs(u0 - centre) - half) / w_input
    phi[:, k + 7:k + 9] = (np.abs(u0 - u_prev) - rate) / w_rate
    out[:, N_TRACK:] = _hinge(phi, shape.sharpness)
    return out
