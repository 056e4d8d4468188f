"""What a planner may know beside the observation: the static scene description an env publishes.

``env.unwrapped.scene`` is a frozen :class:`Scene`, rebuilt at every ``reset`` (the road is randomized). This module
is also the one definition of what the env and the planners must read alike:

- the observation layout (:data:`EGO_FIELDS` ...), built by :func:`join_obs` and read only by :func:`split_obs`
  (numpy or JAX: the jitted planner core slices by the same static indices);
- the input and rate constraint values (paper eq. 4-5, :func:`bound_constraints`), which the env's
  ``info["constraints"]`` reports and the planning problem's barriers measure;
- what the closed-loop score reads per step (:func:`attribution_info`: ``info["contact"]`` and
  ``info["speed_limit"]``), which both kinds of env report alike;
- the scenarios' vehicle and actuators (:data:`VEHICLE_LENGTH` ...), which the env simulates and the vehicle models
  of :mod:`bimp.planners.dynamics` mirror without loading highway-env.

Nothing here imports highway-env or JAX.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from bimp.envs.road import RoadGeometry, Route, array_module, rect_gap, wrap_angle

# --- the scenarios' vehicle and actuators -----------------------------------------------------------------------
# highway-env's Vehicle.LENGTH, WIDTH and MAX_SPEED (tests/envs/test_scenarios.py pins them): here so that the vehicle
# models, which must not load highway-env and pygame, read the very numbers the env simulates.
POLICY_FREQUENCY = 10  # Hz: simulation and policy steps alike
DT = 1.0 / POLICY_FREQUENCY  # s, one policy step
VEHICLE_LENGTH, VEHICLE_WIDTH = 5.0, 2.0  # m
MAX_SPEED = 40.0  # m/s: highway-env's Vehicle.clip_actions pulls any faster vehicle back to it
ACTUATOR_ACCEL = (-10.0, 10.0)  # m/s^2 at the normalized actions -1 and +1
ACTUATOR_STEER = (-0.3, 0.3)  # rad

# --- the observation layout -------------------------------------------------------------------------------------
EGO_FIELDS = ("x", "y", "heading", "speed")
INPUT_FIELDS = ("acceleration", "steering")  # the physical input applied last
OV_FIELDS = ("present", "x", "y", "heading", "speed", "acceleration")
REF_FIELDS = ("speed", "acceleration", "lane_offset")
# Bound of the observation Box: finite (SB3 and check_env dislike infinite boxes), beyond any road here (< 1 km).
OBS_BOUND = 1e4


def split_obs(obs, n_obstacles: int):
    """The one reading of the observation layout: ``obs (..., obs_dim)`` -> ego ``[x, y, heading, speed] (..., 4)``,
    previous input ``[a, delta] (..., 2)``, OVs ``(..., n_obstacles, 6)`` with columns :data:`OV_FIELDS`, reference
    ``[v_ref, a_ref, l_ref] (..., 3)``. Static slices of numpy or JAX arrays alike (inside ``jit`` too), no copy."""
    i = len(EGO_FIELDS)
    k = i + len(INPUT_FIELDS)
    r = k + n_obstacles * len(OV_FIELDS)
    ovs = obs[..., k:r].reshape(*obs.shape[:-1], n_obstacles, len(OV_FIELDS))
    return obs[..., :i], obs[..., i:k], ovs, obs[..., r:]


def join_obs(ego, u_prev, ovs, ref) -> np.ndarray:
    """The inverse of :func:`split_obs` for one observation: ``(obs_dim,)`` from ego ``(4,)``, previous input
    ``(2,)``, OV rows ``(n_obstacles, 6)`` and reference ``(3,)``."""
    return np.concatenate([ego, u_prev, np.ravel(ovs), ref])


# --- the input and rate constraints (eq. 4-5) -------------------------------------------------------------------
BOUND_CONSTRAINTS = ("accel_min", "accel_max", "steer", "accel_rate", "steer_rate")


def travel(speed: ArrayLike, accel: ArrayLike, t: ArrayLike):
    """Distance [m] covered by time ``t`` [s] from ``speed`` [m/s] at constant ``accel`` [m/s^2], stopping rather than
    reversing: the rule by which the planners predict the OVs (numpy or JAX, broadcast)."""
    xp = array_module(speed, accel, t)
    t_stop = xp.where(accel < 0, speed / xp.maximum(-accel, 1e-9), xp.inf)
    tc = xp.minimum(t, t_stop)
    return speed * tc + 0.5 * accel * tc**2


def bound_constraints(bounds, u, du, keep=1.0):
    """The input and rate bounds (paper eq. 4-5) as values that are <= 0 when satisfied, ``(..., 5)`` in the order of
    :data:`BOUND_CONSTRAINTS`: ``a_min - a``, ``a - a_max``, ``|delta| - delta_max``, ``|da| - da_max``,
    ``|ddelta| - ddelta_max``, for inputs ``u (..., 2)`` ``[a m/s^2, delta rad]`` and their increments per policy
    step ``du (..., 2)``.

    The one definition: the env's ``info["constraints"]`` reports it, the planning problem's barriers
    (:func:`bimp.planners.problem.measure`) measure it. ``bounds``: a :class:`Bounds` or the problem's ``Limits``
    (``accel (2,)``, ``steer``, ``accel_rate``, ``steer_rate``; numbers or traced). ``keep``: the bounds scaled by it
    about their centre (the planners aim a little inside). numpy or JAX, the module following the inputs.
    """
    xp = array_module(u, du, bounds.accel)
    lo, hi = bounds.accel[0], bounds.accel[1]
    # Both acceleration bounds from the offset to the centre of the range: their larger value is then exactly
    # (bit for bit) |a - centre| - half, the one barrier the planners put on the pair.
    offset = u[..., 0] - keep * (lo + hi) / 2
    half = keep * (hi - lo) / 2
    return xp.stack([-offset - half, offset - half, xp.abs(u[..., 1]) - keep * bounds.steer,
                     xp.abs(du[..., 0]) - keep * bounds.accel_rate, xp.abs(du[..., 1]) - keep * bounds.steer_rate],
                    axis=-1)


def constraint_values(bounds, u, u_prev, gaps, edge: float) -> dict:
    """What an env's ``info["constraints"]`` reports, every value <= 0 when satisfied: the input and rate bounds
    (:func:`bound_constraints` of the input ``u (2,)`` applied after ``u_prev (2,)``), ``ov_distance`` (``d_min``
    less each footprint gap ``gaps (K,)``) and ``road_edge`` (the edge margin less the edge distance ``edge`` [m])."""
    return {**dict(zip(BOUND_CONSTRAINTS, bound_constraints(bounds, u, u - u_prev).tolist())),
            "ov_distance": (bounds.d_min - np.asarray(gaps, float)).tolist(), "road_edge": bounds.edge_margin - edge}


# --- what the closed-loop score reads (docs/suite.md) -----------------------------------------------------------
# info["contact"]'s keys: the collided OV's centre in the EV's body frame [m] and its heading relative to the EV's
# [rad], both vehicles' speeds [m/s] and the EV's lateral speed relative to its road [m/s].
CONTACT_FIELDS = ("rel_x", "rel_y", "rel_heading", "ev_speed", "ov_speed", "ev_lateral_speed")


def attribution_info(ego: ArrayLike, ovs: ArrayLike, gaps: ArrayLike, ev_lateral_speed: float, speed_limit: float,
                     crashed: ArrayLike | None = None) -> dict:
    """The per-step ``info`` the closed-loop score's at-fault rule and speed terms read
    (:func:`bimp.agents.evaluation.metrics.episode_metrics`), one definition for the paper's envs and the highway-env
    adapter: ``{"contact": dict | None, "speed_limit": float}``.

    ``ego``: the EV's ``[x, y, heading, speed]`` (m, rad, m/s); ``ovs (K, >=5)``: OV rows ``[present, x, y, heading,
    speed, ..]`` (:data:`OV_FIELDS`); ``gaps (K,)``: their footprint gaps [m] (:meth:`Scene.ov_gaps`);
    ``ev_lateral_speed`` [m/s]: the EV's speed across its road, positive to the right as the road's ``l``;
    ``speed_limit`` [m/s, finite, >= 0]: the limit the EV drives under now (each env says which; ValueError
    otherwise); ``crashed (K,)`` bools, or None:
    the OVs the simulator itself reports crashed (highway-env's flags), asked only when no gap is <= 0 (highway-env
    may have pushed a crashed pair apart).

    ``contact`` is None when no OV touches the EV; otherwise the OV with the least gap among those with a gap <= 0
    (else among ``crashed``), as :data:`CONTACT_FIELDS`: ``rel_x``, ``rel_y`` its centre in the EV's body frame (x
    forward, y to the right, as the road's ``l``), ``rel_heading`` its heading less the EV's in [-pi, pi),
    ``ev_speed``, ``ov_speed``, ``ev_lateral_speed``. Plain floats: a trace keeps it as JSON.
    """
    ego, ovs = np.asarray(ego, float), np.atleast_2d(np.asarray(ovs, float))
    gaps = np.asarray(gaps, float).reshape(-1)
    limit = float(speed_limit)
    if not (np.isfinite(limit) and limit >= 0.0):  # 0: a scenario whose free-road speed is a standstill
        raise ValueError(f"speed_limit must be a finite speed >= 0 m/s, got {speed_limit!r}")
    touching = gaps <= 0.0
    if not touching.any() and crashed is not None:
        touching = np.asarray(crashed, bool).reshape(-1)[:len(gaps)]
    if not touching.any():
        return {"contact": None, "speed_limit": limit}
    k = int(np.argmin(np.where(touching, gaps, np.inf)))
    dx, dy = ovs[k, 1:3] - ego[:2]
    c, s = np.cos(ego[2]), np.sin(ego[2])
    contact = {"rel_x": float(c * dx + s * dy), "rel_y": float(-s * dx + c * dy),
               "rel_heading": float(wrap_angle(ovs[k, 3] - ego[2])), "ev_speed": float(ego[3]),
               "ov_speed": float(ovs[k, 4]), "ev_lateral_speed": float(ev_lateral_speed)}
    return {"contact": contact, "speed_limit": limit}


def real_array(values, what: str = "array") -> np.ndarray:
    """``values`` as a numpy array of real numbers (ints or floats, any shape); ``ValueError`` naming the dtype
    otherwise. A float conversion would take a complex value without its imaginary part (numpy only warns), a
    bool as 0/1 and a numeric string as its number: none of them is an observation."""
    array = np.asarray(values)
    if array.dtype.kind not in "iuf":
        raise ValueError(f"{what} must hold real numbers (an int or float dtype), got dtype {array.dtype}")
    return array


@dataclass(frozen=True)
class Bounds:
    """Planning constraints (paper eq. 2-5). The actuators reach further, so violations are measurable.

    accel: (a_min, a_max) [m/s^2]; steer: |delta| <= steer [rad]; accel_rate / steer_rate: bound on the
    change of the commanded input per policy step [m/s^2 per step, rad per step]; d_min: least gap between
    the EV's and an OV's footprints [m]; edge_margin: least distance of every body corner to the road edge [m].
    The input and rate constraint values: :func:`bound_constraints`.
    """

    accel: tuple[float, float] = (-7.0, 3.0)
    steer: float = 0.05
    accel_rate: float = 1.0
    steer_rate: float = 0.005
    d_min: float = 1.0
    edge_margin: float = 0.0


@dataclass(frozen=True)
class Scene:
    """Static description of one episode's scene.

    ``road``: the road a planner knows (:class:`bimp.envs.road.Route`, the EV's route as a polyline with its
    drivable area); an env whose road changes as the EV drives (a wrapped highway-env env) publishes a new scene each
    step. ``actuator_accel`` / ``actuator_steer``: physical ranges that the normalized action [-1, 1] maps onto.
    ``n_obstacles``: fixed number of OV slots in the observation (absent ones are masked, ``present = 0``).
    ``geometry``: the closed-form road where the env has one (the paper's scenarios: what NMPC's CasADi program
    plans on), else None. ``ov_paths``: where the env knows where the OVs drive (a wrapped highway-env junction
    road: :mod:`bimp.envs.highway.prediction`), each slot's path ``(n_obstacles, T, 3)`` ``[x, y, heading]`` every
    ``dt`` from now, which the planners predict the OVs along; None elsewhere (they extrapolate the observation).
    Per step, like the road a wrapped env republishes, and left out of the comparison of scenes. ``lane_path``: the
    reference's lane leads through several lanes in a row (exit-v0's plan through the gaps), so the planners track
    the heading of its path too (:func:`bimp.planners.problem.reference_profile`); False: the heading term aims
    along the road. ``on_lanes``: where the route's edges leave out drivable lanes beside it (a wrapped highway-env
    road, at a junction: the ring beside a roundabout's entry), whether points ``(P, 2)`` all lie on a lane (the
    road-edge guard's test, :mod:`bimp.planners.guard`); None: the route's edges bound the whole drivable area.
    ``edge_guard``: the road asks its planners to brake in lane rather than
    apply a plan that leaves it (EnKTS's and EnKS's road-edge guard at ``road_guard`` None): every wrapped highway-env
    road and family; False on the paper's scenarios, where the planners are the paper's as printed.
    """

    road: Route
    bounds: Bounds
    dt: float
    vehicle_length: float
    vehicle_width: float
    actuator_accel: tuple[float, float]
    actuator_steer: tuple[float, float]
    n_obstacles: int
    geometry: RoadGeometry | None = None
    ov_paths: np.ndarray | None = field(default=None, compare=False)
    lane_path: bool = False
    on_lanes: Callable[[np.ndarray], bool] | None = field(default=None, compare=False)
    edge_guard: bool = False

    # --- observation layout --------------------------------------------------------------------------
    @property
    def obs_dim(self) -> int:
        return len(EGO_FIELDS) + len(INPUT_FIELDS) + self.n_obstacles * len(OV_FIELDS) + len(REF_FIELDS)

    def split_obs(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:func:`split_obs` of ``obs (obs_dim,)`` as float64: ego ``(4,)``, previous input ``(2,)``, OVs
        ``(n_obstacles, 6)``, reference ``(3,)``."""
        return split_obs(np.asarray(obs, dtype=float), self.n_obstacles)

    def check_obs(self, obs: np.ndarray) -> np.ndarray:
        """Validate an observation for a policy: real numbers (:func:`real_array`), right shape, finite. Returns it
        as float64."""
        obs = real_array(obs, "observation").astype(float)
        if obs.shape != (self.obs_dim,):
            raise ValueError(f"observation has shape {obs.shape}, expected ({self.obs_dim},)")
        if not np.all(np.isfinite(obs)):
            bad = np.flatnonzero(~np.isfinite(obs)).tolist()
            raise ValueError(f"observation holds non-finite values at indices {bad}")
        return obs

    # --- actions ---------------------------------------------------------------------------------------
    @property
    def actuator_range(self) -> tuple[np.ndarray, np.ndarray]:
        """Physical ``[a, delta]`` at the normalized actions -1 and +1: ``(low (2,), high (2,))``."""
        return (np.array([self.actuator_accel[0], self.actuator_steer[0]]),
                np.array([self.actuator_accel[1], self.actuator_steer[1]]))

    def to_physical(self, action: np.ndarray) -> np.ndarray:
        """Normalized action ``(..., 2)`` in [-1, 1] -> ``[a m/s^2, delta rad]`` (clipped first)."""
        a = np.clip(np.asarray(action, float), -1.0, 1.0)
        lo, hi = self.actuator_range
        return lo + (a + 1.0) * (hi - lo) / 2.0

    def to_normalized(self, u: np.ndarray) -> np.ndarray:
        """Physical input ``(..., 2)`` -> normalized action in [-1, 1] (clipped to the actuator range)."""
        lo, hi = self.actuator_range
        return np.clip(2.0 * (np.asarray(u, float) - lo) / (hi - lo) - 1.0, -1.0, 1.0)

    # --- geometry --------------------------------------------------------------------------------------
    def edge_distance(self, states: np.ndarray) -> np.ndarray:
        """Least signed distance [m] of the body corners to the drivable area's edges, ``(...)`` for ``states
        (..., 4)`` (:meth:`bimp.envs.road.Route.edge_distance`)."""
        return self.road.edge_distance(states, self.vehicle_length, self.vehicle_width)

    def ov_gaps(self, ego: np.ndarray, ovs: np.ndarray) -> np.ndarray:
        """Footprint gaps [m] ``(K,)`` between the ego state ``[x, y, heading, ..] (>=3,)`` and OV rows ``(K, >=4)``
        of ``[present, x, y, heading, ..]`` (:data:`OV_FIELDS`); ``inf`` where an OV is absent.

        The exact signed distance between the two ``vehicle_length`` x ``vehicle_width`` rectangles at their
        positions and headings (:func:`bimp.envs.road.rect_gap`): > 0 apart, 0 touching, < 0 overlapping (minus the
        penetration depth). The env's ``info["collision"]`` is ``min(ov_gaps) <= 0``.
        """
        ego, ovs = np.asarray(ego, float), np.atleast_2d(np.asarray(ovs, float))
        gap = rect_gap(ego[:2], ego[2], ovs[:, 1:3], ovs[:, 3], self.vehicle_length, self.vehicle_width)
        return np.where(ovs[:, 0] > 0, gap, np.inf)


def scene_batch(scenes: Scene | Sequence[Scene]) -> list[Scene]:
    """A scene, or a batch's scenes, as the batch's list (a scene alone: a batch of one)."""
    return [scenes] if isinstance(scenes, Scene) else list(scenes)


def asks_guard(scenes: Scene | Sequence[Scene]) -> bool:
    """Whether ``scenes`` (a scene, or a batch's) ask for the road-edge guard (``Scene.edge_guard``); a batch that
    mixes roads that ask with roads that do not is refused (one planner config holds one guard)."""
    asks = {s.edge_guard for s in scene_batch(scenes)}
    if not asks:
        raise ValueError("no scene to ask: a batch needs at least one")
    if len(asks) > 1:
        raise ValueError("a batch mixes roads that ask for the road-edge guard (Scene.edge_guard) with roads that "
                         "do not: plan them in separate batches")
    return asks.pop()


def leads(scenes: Scene | Sequence[Scene]) -> bool:
    """Whether ``scenes`` (a scene, or a batch's) have a reference lane that leads through lanes
    (``Scene.lane_path``: :func:`bimp.planners.problem.for_road`)."""
    return any(s.lane_path for s in scene_batch(scenes))
