"""The planning problem, defined once: the virtual system of the paper (eq. 2-8) as immutable pytrees and pure
functions.

EnKTS/EnKS (:mod:`bimp.planners.core`, JAX) and MPPI (numpy) share these definitions; NMPC's CasADi expressions are
pinned to them by tests. Every function takes numpy or JAX arrays and answers in kind (the array module follows the
inputs). The input and rate bounds are measured by the env's own function (:func:`bimp.envs.scene.bound_constraints`),
so the numbers a plan is measured against are the numbers the env reports.

Per horizon step ``t`` a particle carries ``xb = [x (4), u (2), du (2)]``: state ``x = [x m, y m, heading rad,
speed m/s]``, input ``u = [a m/s^2, delta rad]``, its increment ``du``. The virtual measurement of the state
``x_{t+1} = f(x_t, u_t)`` reached by the step's input, ``y = [r (3), s (2), z (K + 9)]``, is observed as all zeros
(eq. 8):

- reference state ``r``, in road coordinates: lateral offset to the reference lane [m], heading relative to the
  road [rad], speed minus the reference speed [m/s] (tracking a world position would pull the EV to a point; the
  longitudinal position is left free);
- reference input ``s``: acceleration minus the reference speed's rate [m/s^2], steering minus the road
  curvature's feedforward angle [rad];
- barriers ``z = psi(phi)``, one per constraint family (a vector, not a sum, so the ensemble regression can tell
  which constraint a particle breaks): each OV's keep-out (eq. 2), the road edges (eq. 3), the acceleration and
  steering bounds (eq. 4), their rates (eq. 5), and the same four for the first control ``u_0`` (the applied one,
  which the smoothing keeps revising long after its own step). ``psi`` is a softplus hinge of ``phi / width``:
  finite, smooth, about 0 when satisfied, so a constraint reads like a measurement of 0 with noise
  ``sigma_barrier``, the barriers' tightness.

The keep-out inflates the footprint by a time headway and the braking room: ahead of an OV the EV needs
``length + d_min + headway * v + room`` of road, so the danger enters the horizon while braking still suffices.
Every planner measures the states ``x_1 .. x_H``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple, TypeVar

import numpy as np

from bimp.configs import ConfigError, added_field, check_fields, load_config, load_layered
from bimp.envs.road import Route, array_module, project, wrap_angle
from bimp.envs.scene import Bounds, Scene, bound_constraints, travel
from bimp.planners.dynamics import check_dynamics

N_TRACK = 5  # r (3) + s (2)
N_BOUND_BARRIERS = 9  # road edge, accel, steer, accel rate, steer rate, and the four of the first control
N_FIRST_CONTROL = 4  # the last rows of y: the first control's bounds
BARRIERS = ("ov (one per OV)", "road_edge", "accel", "steer", "accel_rate", "steer_rate",
            "first accel", "first steer", "first accel_rate", "first steer_rate")
ACTIVE = 1e-3  # a barrier below this for every particle carries no information (see planners.core)
# Least degrees of freedom a planner takes (see ProblemConfig): the planners work in float32, where a nu just
# above 2 rounds to 2 and every plan is non-finite.
NU_MIN = 2.1


# --- configuration of the problem (the shared tuning of every planner) --------------------------------------
@dataclass(frozen=True)
class BarrierShape:
    """Margins and widths of the barriers.

    headway [s]: time gap added to ``d_min`` behind (or ahead of) an OV; follower_decel [m/s^2]: the braking
    the follower (the EV behind an OV, or an OV behind the EV) is assumed to shed its closing speed with, which
    sets the braking room (not an OV's braking in a scenario: that is the env's ``brake_decel``);
    lateral_clearance [m]: least side gap between footprints; edge_margin [m]: least corner distance to the edge
    the planner aims for; bound_margin: fraction by which the planner tightens the input and rate bounds (the
    barriers are soft: the ensemble mean settles a little past where they start to read); widths: the constraint
    violation that makes a barrier read 1, per family, in its own units [share of the keep-out box, m, m/s^2, rad,
    m/s^2, rad]; sharpness: softplus sharpness in those normalized units. Checked by
    :func:`bimp.configs.check_fields`, then headway, lateral_clearance >= 0, follower_decel, widths, sharpness > 0,
    bound_margin in [0, 1): a bad value raises :class:`bimp.configs.ConfigError` naming it.
    """

    headway: float = 0.6
    follower_decel: float = 6.0
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
        for key in ("follower_decel", "sharpness"):
            if not getattr(self, key) > 0:
                raise ConfigError(key, "> 0", getattr(self, key))
        if min(self.widths) <= 0:
            raise ConfigError("widths", "a list of 6 numbers > 0", self.widths)
        if not 0 <= self.bound_margin < 1:
            raise ConfigError("bound_margin", "in [0, 1)", self.bound_margin)


PROBLEM_FILE = "problem.yaml"


@dataclass(frozen=True)
class ProblemConfig:
    """The planning problem's tuning, shared by every planner (``configs/problem.yaml``): the virtual system of
    eq. 7-8.

    horizon: H >= 1 steps, the same for every planner; nu: degrees of freedom >= ``NU_MIN`` = 2.1 of the
    Student's-t process and measurement noise (``inf``: Gaussian, as for EnKS). The floor is where nu works in
    float32, not where the distribution ends (> 2): ``nu = 2.000000000001`` rounds to 2, the noise's covariance
    factor ``nu / (nu - 2)`` is infinite and every plan non-finite (each one fell back on a test episode); just
    above, ``nu - 2`` keeps a bit or two of precision and the draws millions of times the nominal variance. From
    2.1 the factor is at most 21 (``bimp tune`` searches from 2.5). sigma_du: process noise scale of the control
    increments ``[da m/s^2, ddelta rad]`` per step; sigma_ref: measurement noise of the reference state
    ``[lateral m, heading rad, speed m/s]``; sigma_input: of the reference input ``[a m/s^2, delta rad]``;
    sigma_barrier: of each barrier value (the barriers' tightness);
    lane_change_rate [m/s]: the reference lane over the horizon leaves the EV's lateral offset toward the
    reference lane at most this fast, a lane-change path rather than a step (``inf``: the step);
    track_course: the heading term measures the course (the direction of travel, the body's heading plus the
    bicycle's slip ``arctan(tan(delta) / 2)``) against the road's heading instead of the body's heading (what
    :func:`for_road` turns on on a road whose steering bound is not the paper's); barrier: margins and widths
    (:class:`BarrierShape`); road_points, road_spacing [m]: the road the planner
    sees, P points of the scene's route every ``road_spacing`` m from ``ROAD_BEHIND`` m behind the EV (one compiled
    program per P; the plan's reach at 40 m/s over 2 s is 80 m, the default window 139 m); dynamics: ``"mlp"`` (the
    shipped model), ``"bicycle"``
    (the exact model) or the path of a weights file written by ``bimp train-dynamics`` (checked when the config is
    built). A bad value raises :class:`bimp.configs.ConfigError` naming the key and the value.

    Every planner's config holds one as its ``problem`` (``--set POLICY.problem.horizon=30`` means the same for
    each); :func:`load_planner_config` builds them in layers from ``configs/problem.yaml``.
    """

    horizon: int = 20
    nu: float = 4.0
    sigma_du: tuple[float, float] = (0.5, 0.002)
    sigma_ref: tuple[float, float, float] = (1.0, 0.05, 2.0)
    sigma_input: tuple[float, float] = (3.0, 0.02)
    sigma_barrier: float = 0.1
    lane_change_rate: float = math.inf
    barrier: BarrierShape = field(default_factory=BarrierShape)
    dynamics: str = "mlp"
    # The general road (issue 26): no value reproduces the closed-form road of before, so these are plain fields
    # and every planner's config hash changed with them (docs/evaluation.md).
    road_points: int = 160
    road_spacing: float = 1.0
    track_course: bool = added_field(False, neutral=False)

    def __post_init__(self) -> None:
        check_fields(self, allow_inf=("nu", "lane_change_rate"))
        if self.road_points < 2:
            raise ConfigError("road_points", "an int >= 2", self.road_points)
        if not 0.1 <= self.road_spacing <= 10.0:
            raise ConfigError("road_spacing", "in [0.1, 10] m", self.road_spacing)
        if self.horizon < 1:
            raise ConfigError("horizon", "an int >= 1", self.horizon)
        if not self.nu >= NU_MIN:
            raise ConfigError("nu", f">= {NU_MIN} (inf: Gaussian; see ProblemConfig)", self.nu)
        if not self.lane_change_rate > 0:
            raise ConfigError("lane_change_rate", "> 0 m/s (inf: a step)", self.lane_change_rate)
        for key in ("sigma_du", "sigma_ref", "sigma_input", "sigma_barrier"):
            value = getattr(self, key)
            if min(np.atleast_1d(value)) <= 0:
                raise ConfigError(key, "> 0" if key == "sigma_barrier" else "a list of numbers > 0", value)

        check_dynamics(self.dynamics)


# --- the problem as pytrees -----------------------------------------------------------------------------------
class Road(NamedTuple):
    """The road ahead as traced arrays, ``(P,)`` each (``xy (P, 2)``): a window of the scene's
    :class:`bimp.envs.road.Route` with the same fields (:func:`bimp.envs.road.project` reads both), so a new road is
    new data, not a new program."""

    xy: np.ndarray
    s: np.ndarray
    heading: np.ndarray
    curvature: np.ndarray
    left: np.ndarray
    right: np.ndarray


ROAD_BEHIND = 20.0  # m of road behind the EV in the planner's window: OVs beside and just behind it


class Limits(NamedTuple):
    """Planning bounds (eq. 2-5), vehicle size and actuator ranges. ``accel (2,)``; ``actuator_lo/hi (2,)``."""

    accel: np.ndarray
    steer: float
    accel_rate: float
    steer_rate: float
    d_min: float
    length: float
    width: float
    dt: float
    actuator_lo: np.ndarray
    actuator_hi: np.ndarray


class Barrier(NamedTuple):
    """:class:`BarrierShape` as numbers; ``widths (6,)``."""

    headway: float
    follower_decel: float
    lateral_clearance: float
    edge_margin: float
    widths: np.ndarray
    sharpness: float
    bound_margin: float


class Problem(NamedTuple):
    """One episode's planning problem: ``noise (m,)`` is the measurement noise scale of each row of ``y``;
    ``model`` the dynamics' parameters (:mod:`bimp.planners.model`); ``lane_rate`` the reference lane's lateral speed
    [m/s] over the horizon (finite: a step is 1e6); ``course``: 1.0 where the heading term measures the course
    (``ProblemConfig.track_course``), else 0.0 (data, not a program switch); ``lane_heading``: 1.0 where the heading
    term aims along the reference lane's path (``Scene.lane_path``: :func:`reference_profile`), else 0.0 (data);
    ``paths``: the OVs' paths where the
    scene gives them (``Scene.ov_paths (K, T, 3)``, :func:`predict_obstacles`), else None (a program switch: a
    junction road compiles its own program)."""

    road: Road
    limits: Limits
    barrier: Barrier
    noise: np.ndarray
    model: tuple
    lane_rate: float
    course: float = 0.0
    paths: np.ndarray | None = None
    lane_heading: float = 0.0


STEER_UNIT = Bounds().steer  # rad: the paper's steering bound, where the steering's noise scales were tuned


def for_road(config: ProblemConfig, steer: float, lane_path: bool = False) -> ProblemConfig:
    """``config`` on a road whose planning steering bound is ``steer`` [rad], where it is not the paper's
    :data:`STEER_UNIT` (the paper's scenarios, the suite and the straight roads keep ``config`` as it is), and on a
    road whose reference lane leads through the gaps of several lanes (``lane_path``: exit-v0, ``Scene.lane_path``):

    - the steering's noise (``sigma_du``'s and ``sigma_input``'s, tuned at the paper's bound) scales by ``steer /
      STEER_UNIT``, so that it measures the same share of the steering range on every road. At the paper's scales a
      junction's turn (0.37 rad of feed-forward at intersection-v0) lay 50 increments' standard deviations beyond a
      start from standstill: the smoothing never found it, held the EV at the stop line (every planner) or cut the
      turn's inside to its edge. The barriers' widths are not scaled: a bound's barrier reads violations in radians
      on every road;
    - the heading term tracks the course (``track_course``). On a tight curve the bicycle's body points outward of
      its course by the slip (0.12 rad on roundabout-v0's ring, 2.4 of the heading's 0.05 rad sigmas): aligning the
      body with the lane turned the course inward, and the plans settled 1-2 m inside the lane (into the ring's
      inner lane, past the exit), or drifted off it while stopping in the roundabout's S-bend entry. On the paper's
      roads the slip is at most 0.025 rad;
    - with ``lane_path``, no time headway in the OVs' keep-out boxes (``barrier.headway`` 0: the least gap and the
      braking room stay). The behaviour layer picks the gap to change into by a gap and a braking room of its own
      (``bimp.envs.highway.gaps``), and the planners' 0.6 s headway refused most of them (exit-v0's exit lane on 4
      of development seeds 0-11 with it, 9 without: docs/studies/highway-env-history.md).

    :func:`road_changes` lists what this changes, for the record."""
    k = float(steer) / STEER_UNIT
    if k != 1.0:
        config = dataclasses.replace(config, sigma_du=(config.sigma_du[0], config.sigma_du[1] * k),
                                     sigma_input=(config.sigma_input[0], config.sigma_input[1] * k), track_course=True)
    if lane_path:
        config = dataclasses.replace(config, barrier=dataclasses.replace(config.barrier, headway=0.0))
    return config


def road_changes(config: ProblemConfig, steer: float, lane_path: bool = False) -> dict:
    """The fields of ``config`` that :func:`for_road` changes on a road of steering bound ``steer`` [rad] (and
    ``lane_path``), as ``{key: new value}`` (``{}`` where it changes none): what a planner records beside its
    config, so that its episodes on such a road are attributed to what it planned with."""
    adapted = for_road(config, steer, lane_path)
    return {f.name: getattr(adapted, f.name) for f in dataclasses.fields(config)
            if getattr(adapted, f.name) != getattr(config, f.name)}


def measurement_noise(config: ProblemConfig, n_obstacles: int) -> np.ndarray:
    """The noise scale of each row of ``y`` ``(m,)``: reference state, reference input, the barriers."""
    return np.array([*config.sigma_ref, *config.sigma_input]
                    + [config.sigma_barrier] * (n_obstacles + N_BOUND_BARRIERS))


def search_space() -> dict:
    """The planning problem's numbers ``bimp tune`` searches, for every planner built on it (optuna
    distributions), keyed as in a planner's config (``problem.*``): the noise of the increments and of the tracked
    reference (lateral, speed), the edge margin and the headway."""
    from optuna.distributions import FloatDistribution as Float

    return {
        "problem.sigma_du[0]": Float(0.2, 1.5, log=True),
        "problem.sigma_du[1]": Float(0.0005, 0.005, log=True),
        "problem.sigma_ref[0]": Float(0.3, 3.0, log=True),
        "problem.sigma_ref[2]": Float(0.3, 3.0, log=True),
        "problem.barrier.edge_margin": Float(0.1, 0.8),
        "problem.barrier.headway": Float(0.3, 1.2),
    }


def load_problem(source=PROBLEM_FILE, **overrides) -> ProblemConfig:
    """The shared problem tuning: ``configs/problem.yaml`` (or ``source``) plus ``overrides``."""
    return load_config(ProblemConfig, source, **overrides)


C = TypeVar("C")
Layer = str | Path | Mapping[str, Any] | None


# Settings renamed since results were recorded: {old dotted key: new}, refused under the old name when loaded
# (naming the new one) and renamed by `bimp migrate` in the records.
RENAMED = {"problem.barrier.brake_decel": "problem.barrier.follower_decel"}


def load_planner_config(cls: type[C], *layers: Layer) -> C:
    """A planner's config ``cls`` (its own fields and ``problem``, a :class:`ProblemConfig`) built in layers by
    :func:`bimp.configs.load_layered`: ``cls``'s defaults, the shared problem (``configs/problem.yaml``) as its
    ``problem``, then ``layers`` in order (YAML files of overrides, mappings or None), nested mappings merged key by
    key and dotted keys nested (``{"problem.horizon": 30}``: what ``--set POLICY.problem.horizon=30`` gives).

    A key of the problem given at the top level (``horizon``, ``nu``, ``sigma_du``, ..., the flat keys of EnKTS's
    old config), one that ``cls.MOVED`` names (``{old key: new dotted key}``) or one :data:`RENAMED` names raises
    ``ValueError`` naming its new place: one name per setting, no aliases. Other unknown keys and bad values raise as
    :func:`bimp.configs.load_config` does (:class:`bimp.configs.ConfigError` naming the dotted key)."""
    own = {f.name for f in dataclasses.fields(cls)}
    moved = {f.name: f"problem.{f.name}" for f in dataclasses.fields(ProblemConfig) if f.name not in own}
    moved.update(getattr(cls, "MOVED", {}), **RENAMED)
    return load_layered(cls, *layers, base={"problem": dataclasses.asdict(load_problem())}, moved=moved)


def road_window(route: Route, ego_xy: np.ndarray, config: ProblemConfig) -> Road:
    """The planner's road: ``config.road_points`` points of ``route`` every ``config.road_spacing`` m from
    ``ROAD_BEHIND`` m behind the EV at ``ego_xy (2,)`` (padded straight past the route's ends)."""
    s_ev = float(route.project(np.asarray(ego_xy, float)).s)
    w = route.window(s_ev - ROAD_BEHIND, config.road_points, config.road_spacing)
    return Road(w.xy, w.s, w.heading, w.curvature, w.left, w.right)


def make_problem(scene: Scene, config: ProblemConfig, model: tuple = (), ego_xy: np.ndarray | None = None) -> Problem:
    """The problem of ``scene`` under ``config`` with the road seen from ``ego_xy (2,)`` (the EV's position; the
    route's start if None) (numpy leaves; ``jax.device_put`` or any jnp call takes them)."""
    b = scene.bounds
    config = for_road(config, b.steer, scene.lane_path)
    shape = config.barrier
    lo, hi = scene.actuator_range
    f = float
    return Problem(
        road=road_window(scene.road, scene.road.xy[0] if ego_xy is None else ego_xy, config),
        limits=Limits(np.array(b.accel, float), f(b.steer), f(b.accel_rate), f(b.steer_rate), f(b.d_min),
                      f(scene.vehicle_length), f(scene.vehicle_width), f(scene.dt), lo, hi),
        barrier=Barrier(f(shape.headway), f(shape.follower_decel), f(shape.lateral_clearance), f(shape.edge_margin),
                        np.array(shape.widths, float), f(shape.sharpness), f(shape.bound_margin)),
        noise=measurement_noise(config, scene.n_obstacles),
        model=model,
        lane_rate=f(min(config.lane_change_rate, 1e6)),  # finite: inf * 0 would be nan at t = 0
        course=1.0 if config.track_course else 0.0,
        paths=scene.ov_paths,
        lane_heading=1.0 if scene.lane_path else 0.0,
    )


# --- functions of the problem ---------------------------------------------------------------------------------
def frenet(road: Road, xy):
    """Road coordinates ``(s, l)`` of points ``xy (..., 2)`` (:func:`bimp.envs.road.project`)."""
    p = project(road, xy)
    return p.s, p.l


def edge_distance_local(left, right, limits: Limits, lat, dpsi):
    """The edge distance (eq. 3; exact for the rectangle: :meth:`bimp.envs.scene.Scene.edge_distance`) from the
    centre's road coordinates and the edges ``left < right`` there: the body corners' lateral offsets in the road
    frame at the centre, ``lat +- (L/2 |sin dpsi| + W/2 cos dpsi)``, taken as straight over the car's length.
    What the planners measure (NMPC too, as four smooth rows): a quarter of the transcendental work of the exact
    corners, and within 2 cm of them on the paper's curves (the road bends by (L/2)^2 / 2R = 1.7 cm over half a
    car at R = 180 m; the barrier's edge margin is 0.3 m; a test pins it). On highway-env's tight curves the bend
    is larger: 0.16 m at R = 20 m (roundabout), 0.35 m at R = 9 m (intersection), on the outer corners; the env's
    off-road check is the exact one."""
    xp = array_module(lat, dpsi)
    extent = 0.5 * limits.length * xp.abs(xp.sin(dpsi)) + 0.5 * limits.width * xp.cos(dpsi)
    return xp.minimum(right - lat, lat - left) - extent


def predict_obstacles(problem: Problem, ovs, horizon: int):
    """Constant-acceleration prediction of the OVs along their own heading relative to the road (a vehicle in a
    lane moves along it; an oncoming one against ``s``, a crossing one across it), speed never below 0; where the
    problem has the OVs' paths (``problem.paths``: a junction road's lanes), along those instead.

    ovs: observation rows ``(K, 6)`` ``[present, x, y, heading, speed, accel]``. Returns ``s, l, v, a`` of shapes
    ``(horizon + 1, K)`` (index 0 = now; ``v``, ``a`` along the road, signed: < 0 for oncoming traffic) and
    ``present`` (bool ``(K,)``).
    """
    xp = array_module(ovs, problem.limits.dt, problem.road.xy)
    v0, a = ovs[:, 4], ovs[:, 5]
    t = xp.arange(horizon + 1)[:, None] * problem.limits.dt
    t_stop = xp.where(a < 0, v0 / xp.maximum(-a, 1e-9), xp.inf)
    v = xp.maximum(v0 + a * t, 0.0)
    a_t = xp.where(t < t_stop, a, 0.0)
    if problem.paths is not None:
        return (*_along_paths(problem, problem.paths, horizon, v, a_t), ovs[:, 0] > 0)
    p = project(problem.road, ovs[:, 1:3])
    dh = wrap_angle(ovs[:, 3] - p.heading)
    along, across = xp.cos(dh), xp.sin(dh)
    d = travel(v0, a, t)
    return p.s + along * d, p.l + across * d, along * v, along * a_t, ovs[:, 0] > 0


def _along_paths(problem: Problem, paths, horizon: int, v, a):
    """``s, l, v, a`` ``(horizon + 1, K)`` of the OVs on their paths ``(K, T, 3)`` ``[x, y, heading]`` (one every
    ``dt`` from now), their speed ``v`` and acceleration ``a`` ``(horizon + 1, K)`` taken along the road by the
    paths' heading; past a path's end, straight on at its last step."""
    xp = array_module(paths, problem.road.xy)
    extra = horizon + 1 - paths.shape[1]
    if extra > 0:  # static shapes: a horizon longer than the paths the env gives
        step = (paths[:, -1] - paths[:, -2]) * xp.array([1.0, 1.0, 0.0])
        paths = xp.concatenate([paths, paths[:, -1:] + xp.arange(1, extra + 1)[None, :, None] * step[:, None]], 1)
    paths = xp.swapaxes(paths[:, :horizon + 1], 0, 1)  # (horizon + 1, K, 3)
    p = project(problem.road, paths[..., :2])
    along = xp.cos(wrap_angle(paths[..., 2] - p.heading))
    return p.s, p.l, along * v, along * a


def reference_profile(problem: Problem, ref, ego, horizon: int):
    """The reference over the horizon, ``(horizon + 1,)`` each: speed and its rate, extrapolating
    ``ref = [v_ref, a_ref, l_ref]`` linearly, never below 0; and the lane offset, leaving the lateral offset of
    ``ego (4,)`` toward ``l_ref`` at ``problem.lane_rate``. A lane change asked as a step makes every state of the
    horizon pull for the far lane at once: the plan swerves and overshoots to the far edge (EnKTS left the road so on
    6 of development seeds 200-499 of the overtaking scenario; at 1.5 m/s, on 3). Returns ``v, a, lane, course``:
    ``course`` the heading of the lane's path against the road's, ``arctan(lane rate / v)`` while the lane moves,
    where ``problem.lane_heading`` asks for it (else zeros). Without it the heading term aims along the road and
    holds a lane change to about 1.2 m/s across (a lane in about 4 s on exit-v0, the EV 0.05 rad off the road's
    heading: one of the heading's sigmas)."""
    xp = array_module(ref, ego, problem.limits.dt)
    t = xp.arange(horizon + 1) * problem.limits.dt
    v = xp.maximum(ref[0] + ref[1] * t, 0.0)
    _, lat = frenet(problem.road, ego[:2])
    reach = problem.lane_rate * t
    lane = lat + xp.clip(ref[2] - lat, -reach, reach)
    moving = xp.abs(ref[2] - lat) > reach  # the lane still on its way at t: moving at lane_rate
    rate = xp.where(moving, xp.sign(ref[2] - lat) * problem.lane_rate, 0.0)
    course = problem.lane_heading * xp.arctan(rate / xp.maximum(v, 1.0))
    return v, xp.where(v > 0.0, ref[1], 0.0), lane, course


def measure(problem: Problem, x, u, du, u0, u_prev, ref_lane, v_ref, a_ref, obstacles, ref_course=0.0):
    """``h(xb)`` of eq. 8 without noise, ``(N, m)``, for the states ``x (N, 4)`` reached with inputs ``u (N, 2)``
    (increments ``du (N, 2)``); ``u0 (N, 2)`` the first control, ``u_prev (2,)`` the input applied last;
    ``ref_lane``, ``v_ref``, ``a_ref``, ``ref_course`` the reference at the state's time; ``obstacles``:
    ``(s, l, v, a)`` each ``(K,)`` at that time and ``present (K,)`` (one row of :func:`predict_obstacles`).
    Observed value: zeros.
    """
    xp = array_module(x, u, du, u0, problem.limits.accel, problem.road.xy)
    road, lim, bar = problem.road, problem.limits, problem.barrier
    p = project(road, x[:, :2])
    s, lat = p.s, p.l
    dpsi = wrap_angle(x[:, 2] - p.heading)  # the body's: its corners meet the edges
    # The course is the direction the bicycle moves in: its heading plus the slip of the step's steering.
    course = dpsi + problem.course * xp.arctan(0.5 * xp.tan(u[:, 1]))
    v = x[:, 3]
    feedforward = xp.arctan(lim.length * p.curvature)
    tracking = xp.stack([lat - ref_lane, course - ref_course, v - v_ref, u[:, 0] - a_ref, u[:, 1] - feedforward],
                        axis=1)

    s_o, l_o, v_o, a_o, present = obstacles
    w = bar.widths
    # Keep-out box around each OV (centre to centre): half-sizes of a footprint plus the clearance, longitudinally
    # the time headway of whichever vehicle follows plus its braking room. The barrier is the smaller *relative*
    # penetration, so a vehicle deep in the same lane is pushed to brake, and only a plan that has mostly left the
    # OV's lane gets credit for the lateral escape (within the lane, swerving buys nothing and heads for the edge).
    ds = s[:, None] - s_o
    behind = ds < 0
    v_follow = xp.where(behind, v[:, None], v_o)  # < 0: an oncoming OV, which follows nothing
    v_lead = xp.where(behind, v_o, v[:, None])
    # Braking room: to match a leader that holds speed, closing^2 / 2b; behind an OV predicted to brake to a stop,
    # the difference of the stopping distances (the danger the 2 s horizon alone would see too late).
    room = xp.maximum(v_follow - v_lead, 0.0) ** 2 / (2 * bar.follower_decel)
    a_lead = xp.where(behind, a_o, 0.0)
    stop = v_follow**2 / (2 * bar.follower_decel) - v_lead**2 / (2 * xp.maximum(-a_lead, 1e-6))
    room = xp.maximum(room, xp.where(a_lead < -0.5, stop, 0.0))
    semi_s = lim.length + lim.d_min + bar.headway * xp.maximum(v_follow, 0.0) + room
    semi_l = lim.width + bar.lateral_clearance
    phi_ov = xp.minimum(1.0 - xp.abs(ds) / semi_s, 1.0 - xp.abs(lat[:, None] - l_o) / semi_l)
    phi_ov = xp.where(present, phi_ov / w[0], -1e3)
    keep = 1.0 - bar.bound_margin  # the barriers are soft: aim a little inside the bounds

    def bounds(u, du):
        """Eq. 4-5 as the env reports them (one function), one barrier per acceleration pair: the nearer bound."""
        c = bound_constraints(lim, u, du, keep)
        return xp.stack([xp.maximum(c[:, 0], c[:, 1]), c[:, 2], c[:, 3], c[:, 4]], axis=1) / w[2:6]

    edge = (bar.edge_margin - edge_distance_local(p.left, p.right, lim, lat, dpsi)) / w[1]
    phi = xp.concatenate([phi_ov, edge[:, None], bounds(u, du), bounds(u0, u0 - u_prev)], axis=1)
    return xp.concatenate([tracking, xp.logaddexp(0.0, bar.sharpness * phi) / bar.sharpness], axis=1)


__all__ = ["ACTIVE", "Barrier", "BARRIERS", "BarrierShape", "edge_distance_local", "frenet",
           "Limits", "load_planner_config", "load_problem", "make_problem", "measure",
           "measurement_noise", "N_FIRST_CONTROL", "N_TRACK", "NU_MIN", "predict_obstacles",
           "Problem", "PROBLEM_FILE", "ProblemConfig",
           "reference_profile", "Road", "ROAD_BEHIND", "road_window",
           "for_road", "road_changes", "STEER_UNIT"]
