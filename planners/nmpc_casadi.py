"""NMPC's program as CasADi expressions: the vehicle models, the closed-form road's Frenet frame, the OV keep-out
and the robust cost (:mod:`bimp.planners.nmpc` builds and solves the NLP from them). Each mirrors a numpy function
elsewhere in the package, and the tests check that they agree."""

from __future__ import annotations

import math

import casadi as ca
import numpy as np

from bimp.envs.road import RoadGeometry
from bimp.envs.scene import Scene
from bimp.planners.dynamics import BicycleModel, load_model
from bimp.planners.problem import BarrierShape


def mlp_function(model=None) -> ca.Function:
    """The learned model as a CasADi ``Function f(x (4,), u (2,)) -> x_next (4,)``, float64.

    Same math as :meth:`bimp.planners.dynamics.LearnedDynamics.predict`: feature map of
    :func:`bimp.planners.dynamics.features` (inputs clipped to the actuator ranges, acceleration capped above
    ``max_speed``), three affine maps with two tanh from the folded weights ``model._w``, ``model._b``, body-frame
    change rotated by the heading, next speed clamped at 0 (:func:`bimp.planners.dynamics.apply_change`). Built on MX:
    the layers stay dense matrix products, which CasADi evaluates and differentiates about 3x faster than the
    scalar SX graph (16k products per layer); JIT-compiling them gains nothing. ``model``: a ``LearnedDynamics``
    (default: the shipped one).
    """
    if model is None:
        model = load_model()
    x, u = ca.MX.sym("x", 4), ca.MX.sym("u", 2)
    v = x[3]
    a = ca.fmin(ca.fmax(u[0], model.accel_range[0]), model.accel_range[1])
    a = ca.if_else(v > model.max_speed, ca.fmin(a, model.max_speed - v), a)
    delta = ca.fmin(ca.fmax(u[1], model.steer_range[0]), model.steer_range[1])
    h = ca.vertcat(v, a, delta)
    # The numpy weights are (in, out) for ``rows @ W``; a column vector needs the transpose.
    for i, (w, b) in enumerate(zip(model._w, model._b)):
        h = ca.DM(np.asarray(w, np.float64).T) @ h + ca.DM(np.asarray(b, np.float64))
        if i < len(model._w) - 1:
            h = ca.tanh(h)
    c, s = ca.cos(x[2]), ca.sin(x[2])
    nxt = ca.vertcat(x[0] + c * h[0] - s * h[1], x[1] + s * h[0] + c * h[1], x[2] + h[2], ca.fmax(x[3] + h[3], 0.0))
    return ca.Function("mlp_step", [x, u], [nxt], ["x", "u"], ["x_next"])


def bicycle_function(model=None) -> ca.Function:
    """The exact kinematic bicycle as a CasADi ``Function f(x (4,), u (2,)) -> x_next (4,)``, float64: the same
    math as :meth:`bimp.planners.dynamics.BicycleModel.predict` (tests check they agree). ``model``: a
    ``BicycleModel`` (default: the env's vehicle)."""
    if model is None:
        model = BicycleModel()
    x, u = ca.MX.sym("x", 4), ca.MX.sym("u", 2)
    h, v = x[2], x[3]
    a, delta = u[0], u[1]
    if model.clip_inputs:
        a = ca.fmin(ca.fmax(a, model.accel_range[0]), model.accel_range[1])
        delta = ca.fmin(ca.fmax(delta, model.steer_range[0]), model.steer_range[1])
    a = ca.if_else(v > model.max_speed, ca.fmin(a, model.max_speed - v), ca.if_else(v < 0, ca.fmax(a, -v), a))
    beta = ca.atan(0.5 * ca.tan(delta))
    dt = model.dt
    nxt = ca.vertcat(x[0] + v * ca.cos(h + beta) * dt, x[1] + v * ca.sin(h + beta) * dt,
                     h + v * ca.sin(beta) / (model.length / 2) * dt, ca.fmax(v + a * dt, 0.0))
    return ca.Function("bicycle_step", [x, u], [nxt], ["x", "u"], ["x_next"])


ROAD_PARAMS = ("straight_in", "radius", "arc_angle")


def closed_form(scene: Scene) -> RoadGeometry:
    """The scene's closed-form road, what NMPC's CasADi program is written on; ``ValueError`` for a scene without
    one (a wrapped highway-env env: a polyline route, which the smooth NLP cannot take as it is)."""
    if scene.geometry is None:
        raise ValueError("NMPC plans on a closed-form road (the paper's straight-arc-straight: bimp/Overtaking-v0, "
                         "bimp/EmergencyBrake-v0); this scene's road is a polyline route only (a wrapped "
                         "highway-env env): use enkts, enks, mppi or idm there")
    return scene.geometry


def road_params(road: RoadGeometry) -> np.ndarray:
    """The road's shape as NLP parameters ``(3,)``: ``[straight_in m, radius m, arc_angle rad]``."""
    return np.array([road.straight_in, road.radius, road.arc_angle])


def frenet(x, y, p):
    """Road coordinates ``(s, l)`` of world points, as CasADi expressions (element-wise on rows).

    ``p``: :func:`road_params` (symbols or numbers). Same pieces and the same switching as
    :meth:`bimp.envs.road.RoadGeometry.to_frenet`: the first straight (extended backwards), the arc where the polar
    angle about its centre is >= 0, the second straight past the arc's end. With ``arc_angle = 0`` the arc
    branch is never selected (the second straight starts at ``straight_in``), as in numpy.
    """
    straight_in, radius, arc = p[0], p[1], p[2]
    turn = ca.if_else(arc >= 0, 1.0, -1.0)
    phi_end = ca.fabs(arc)
    cx, cy = straight_in, turn * radius
    dx, dy = x - cx, y - cy
    phi = ca.atan2(dx, -turn * dy)
    on_arc = phi >= 0
    s = ca.if_else(on_arc, straight_in + radius * phi, x)
    lat = ca.if_else(on_arc, turn * (radius - ca.sqrt(dx**2 + dy**2)), y)
    ex, ey = cx + radius * ca.sin(phi_end), cy - turn * radius * ca.cos(phi_end)
    h_end = turn * phi_end
    s_out = straight_in + radius * phi_end + (x - ex) * ca.cos(h_end) + (y - ey) * ca.sin(h_end)
    l_out = -(x - ex) * ca.sin(h_end) + (y - ey) * ca.cos(h_end)
    past = s_out >= straight_in + radius * phi_end
    return ca.if_else(past, s_out, s), ca.if_else(past, l_out, lat)


def heading_at(s, p):
    """Centreline heading [rad] at ``s`` (:meth:`bimp.envs.road.RoadGeometry.heading_at`)."""
    turn = ca.if_else(p[2] >= 0, 1.0, -1.0)
    return turn * ca.fmin(ca.fmax((s - p[0]) / p[1], 0.0), ca.fabs(p[2]))


def curvature_at(s, p):
    """Signed curvature [1/m] at ``s`` (:meth:`bimp.envs.road.RoadGeometry.curvature_at`)."""
    turn = ca.if_else(p[2] >= 0, 1.0, -1.0)
    on_arc = (s >= p[0]) * (s <= p[0] + p[1] * ca.fabs(p[2])) * (ca.fabs(p[2]) > 0)
    return ca.if_else(on_arc, turn / p[1], 0.0)


def keep_out_semi_axes(scene: Scene, shape: BarrierShape, ds, v, v_o, a_o):
    """Semi-axes ``(semi_s, semi_l)`` [m] of the keep-out around an OV, as CasADi expressions.

    The half-sizes of the keep-out box of :func:`bimp.planners.problem.measure` (centre to centre): the footprint
    length plus ``d_min``, the time headway of whichever vehicle follows and its braking room; laterally the
    footprint width plus the clearance. ``ds = s_EV - s_OV`` [m], ``v`` EV speed, ``v_o`` / ``a_o`` OV speed
    [m/s] and acceleration [m/s^2]. The switch at ``ds = 0`` leaves ``(ds / semi_s)^p`` continuous (it is 0 there
    on both sides), so the keep-out constraint stays continuous.
    """
    behind = ds < 0
    v_follow = ca.if_else(behind, v, v_o)
    v_lead = ca.if_else(behind, v_o, v)
    room = ca.fmax(v_follow - v_lead, 0.0) ** 2 / (2 * shape.follower_decel)
    a_lead = ca.if_else(behind, a_o, 0.0)
    stop = v_follow**2 / (2 * shape.follower_decel) - v_lead**2 / (2 * ca.fmax(-a_lead, 1e-6))
    room = ca.fmax(room, ca.if_else(a_lead < -0.5, stop, 0.0))
    semi_s = scene.vehicle_length + scene.bounds.d_min + shape.headway * v_follow + room
    return semi_s, scene.vehicle_width + shape.lateral_clearance


def robust_cost(q, n: int, nu: float):
    """Negative log-density of a residual with squared Mahalanobis norm ``q``: ``q / 2`` (Gaussian, ``nu = inf``)
    or ``(nu + n) / 2 log(1 + q / nu)`` (Student's-t with ``n`` dimensions, paper section IV)."""
    if math.isinf(nu):
        return q / 2
    return (nu + n) / 2 * ca.log1p(q / nu)


__all__ = ["ROAD_PARAMS", "bicycle_function", "closed_form", "curvature_at", "frenet", "heading_at",
           "keep_out_semi_axes", "mlp_function", "road_params", "robust_cost"]
