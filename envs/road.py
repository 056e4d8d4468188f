"""Road geometry shared by the simulator and the planners.

Two descriptions of a road. :class:`Route`, the general road every planner reads: the EV's route as a centreline
polyline with its heading, curvature and the drivable area's edges (:func:`project` puts points on it, numpy or JAX).
:class:`RoadGeometry`, the paper's closed form (a straight, a circular arc and a straight; an arc angle of 0 gives a
straight road), from which the paper's envs build their lanes and sample their route, NMPC writes its CasADi program
and the tests check the polyline. Points are described in road (Frenet) coordinates ``(s, l)``:
``s`` is the arc length along the centreline, ``l`` the lateral offset, positive to the *right* of the
direction of travel (highway-env's convention: +y at heading 0, the bottom of the rendered image).
Lane ``i`` of ``n`` has its centre at ``l = (i - (n - 1) / 2) * lane_width``, so lane 0 is the left lane and
the road edges are at ``l = +-n * lane_width / 2``.

Every query is vectorized over leading dimensions so a planner can ask for all particles at once.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import NamedTuple

import numpy as np


@dataclass(frozen=True)
class RoadGeometry:
    """Straight (``straight_in`` m) + arc (``radius`` m, signed ``arc_angle`` rad, > 0 turns right) + straight.

    Units: metres and radians. Built by the env at every reset and published in ``env.unwrapped.scene``.
    """

    straight_in: float = 100.0
    radius: float = 200.0
    arc_angle: float = 0.0
    straight_out: float = 300.0
    lane_width: float = 4.0
    lanes: int = 2

    def __post_init__(self) -> None:
        if self.radius <= 0 or self.lane_width <= 0 or self.lanes < 1:
            raise ValueError("radius and lane_width must be > 0 and lanes >= 1")
        if abs(self.arc_angle) >= np.pi:
            raise ValueError(f"arc_angle must lie in (-pi, pi), got {self.arc_angle}")
        if self.radius <= self.half_width:
            raise ValueError("radius must exceed the road's half width")

    # --- derived scalars -------------------------------------------------------------------------
    @property
    def half_width(self) -> float:
        """Distance from the centreline to either road edge [m]."""
        return self.lanes * self.lane_width / 2.0

    @property
    def arc_length(self) -> float:
        return self.radius * abs(self.arc_angle)

    @property
    def length(self) -> float:
        return self.straight_in + self.arc_length + self.straight_out

    @property
    def _turn(self) -> float:
        """+1 for a right turn, -1 for a left turn (or straight)."""
        return 1.0 if self.arc_angle >= 0 else -1.0

    # Cached: queried for every particle batch at every horizon step, and the geometry never changes.
    @cached_property
    def _centre(self) -> np.ndarray:
        return np.array([self.straight_in, self._turn * self.radius])

    @cached_property
    def _arc_end(self) -> np.ndarray:
        return self._arc_point(np.array(abs(self.arc_angle)), np.array(0.0))

    def lane_offset(self, lane: int | np.ndarray) -> np.ndarray | float:
        """Lateral offset of lane centre ``lane`` [m]."""
        return (np.asarray(lane) - (self.lanes - 1) / 2.0) * self.lane_width

    # --- queries ---------------------------------------------------------------------------------
    def _arc_point(self, phi: np.ndarray, lat: np.ndarray) -> np.ndarray:
        sigma = self._turn
        r = self.radius - sigma * lat
        return self._centre + np.stack([r * np.sin(phi), -sigma * r * np.cos(phi)], axis=-1)

    def position(self, s: np.ndarray, lat: np.ndarray) -> np.ndarray:
        """World position ``(..., 2)`` of road coordinates ``s``, ``lat`` (any broadcastable shapes)."""
        s, lat = np.broadcast_arrays(np.asarray(s, float), np.asarray(lat, float))
        heading = self.heading_at(s)
        # Straight pieces: walk from the piece's start along the heading; the arc: rotate about its centre.
        s_arc_end = self.straight_in + self.arc_length
        start = np.where((s < self.straight_in)[..., None], 0.0, self._arc_end)
        along = np.where(s < self.straight_in, s, s - s_arc_end)
        t = np.stack([np.cos(heading), np.sin(heading)], axis=-1)
        n = np.stack([-np.sin(heading), np.cos(heading)], axis=-1)
        straight = start + along[..., None] * t + lat[..., None] * n
        if self.arc_length == 0.0:
            return straight
        phi = np.clip((s - self.straight_in) / self.radius, 0.0, abs(self.arc_angle))
        on_arc = (s >= self.straight_in) & (s <= s_arc_end)
        return np.where(on_arc[..., None], self._arc_point(phi, lat), straight)

    def heading_at(self, s: np.ndarray) -> np.ndarray:
        """Centreline heading [rad] at arc length ``s``."""
        return heading_at(np.asarray(s, float), self.straight_in, self.radius, self.arc_angle)

    def curvature_at(self, s: np.ndarray) -> np.ndarray:
        """Signed centreline curvature [1/m] at ``s`` (> 0 turning right)."""
        return curvature_at(np.asarray(s, float), self.straight_in, self.radius, self.arc_angle)

    def to_frenet(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Road coordinates ``(s, l)`` of world points ``xy (..., 2)``, each of shape ``(...)``."""
        return to_frenet(np.asarray(xy, float), self.straight_in, self.radius, self.arc_angle)


    def route(self, spacing: float = 0.5) -> "Route":
        """The road as the general :class:`Route` every planner reads: the centreline sampled every ``spacing`` m
        over the whole length, with its exact heading and curvature and the edges at ``+-half_width``."""
        s = np.linspace(0.0, self.length, int(np.ceil(self.length / spacing)) + 1)
        edge = np.full_like(s, self.half_width)
        return Route(xy=self.position(s, np.zeros_like(s)), s=s, heading=self.heading_at(s),
                     curvature=self.curvature_at(s), left=-edge, right=edge)


@dataclass(frozen=True, eq=False)
class Route:
    """The road as a planner knows it: a centreline polyline along the EV's route (DESIGN section 8).

    ``xy (P, 2)`` points [m], ``s (P,)`` arc length at each (increasing), ``heading (P,)`` [rad, continuous: no
    wrap along the route], ``curvature (P,)`` [1/m, > 0 turning right], ``left``/``right (P,)`` the drivable area's
    edges as signed lateral offsets [m] (``l`` positive to the right, so ``left < right``; the paper's road has
    ``-+half_width``). Between points every quantity is linear in ``s``; before the first point and after the last
    the first and last segments extend straight. Compared by identity (numpy fields); built by the env and published
    in its :class:`bimp.envs.scene.Scene`, read by :func:`project` (numpy or JAX, the planners' problem holds the same
    fields as traced arrays, :func:`window` resamples it to a fixed shape).
    """

    xy: np.ndarray
    s: np.ndarray
    heading: np.ndarray
    curvature: np.ndarray
    left: np.ndarray
    right: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.s)
        if n < 2 or np.shape(self.xy) != (n, 2) or any(np.shape(getattr(self, k)) != (n,)
                                                        for k in ("heading", "curvature", "left", "right")):
            raise ValueError(f"a route needs >= 2 points with xy (P, 2) and s, heading, curvature, left, right (P,); "
                             f"got xy {np.shape(self.xy)}, s {np.shape(self.s)}")
        if not np.all(np.diff(self.s) > 0):
            raise ValueError("a route's s must increase strictly from point to point")
        if not all(np.all(np.isfinite(getattr(self, k))) for k in ("xy", "s", "heading", "curvature", "left",
                                                                      "right")):
            raise ValueError("a route's arrays must be finite")

    @classmethod
    def from_points(cls, xy: np.ndarray, left: np.ndarray, right: np.ndarray) -> "Route":
        """A route through points ``xy (P, 2)`` (distinct, in driving order) with edges ``left``/``right (P,)``:
        ``s`` by cumulative chord, heading and curvature by finite differences (for lanes known only as points)."""
        xy = np.asarray(xy, float)
        d = np.diff(xy, axis=0)
        s = np.concatenate([[0.0], np.cumsum(np.hypot(d[:, 0], d[:, 1]))])
        seg = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
        heading = np.concatenate([[seg[0]], (seg[:-1] + seg[1:]) / 2, [seg[-1]]])
        with np.errstate(divide="ignore", invalid="ignore"):  # repeated points: refused below, naming the cause
            curvature = np.gradient(heading, s) if len(s) > 2 else np.zeros(len(s))
        return cls(xy, s, heading, curvature, np.asarray(left, float), np.asarray(right, float))

    def window(self, s_start: float, points: int, spacing: float) -> "Route":
        """The route resampled at ``points`` arc lengths ``s_start + k * spacing``: one fixed shape for every road,
        so a planner compiles once. Past either end the route extends straight along its end segment (a route that
        ends mid-horizon is padded, never NaN)."""
        if points < 2 or not spacing > 0:
            raise ValueError(f"a window needs points >= 2 and spacing > 0, got {points}, {spacing}")
        s = s_start + spacing * np.arange(points)
        head = np.interp(s, self.s, self.heading)
        xy = self.position(s, np.zeros_like(s))
        return Route(xy=xy, s=s, heading=head, curvature=np.interp(s, self.s, self.curvature),
                     left=np.interp(s, self.s, self.left), right=np.interp(s, self.s, self.right))

    # --- queries (numpy; the planners call project on their traced copy) ---------------------------------------
    def project(self, xy: np.ndarray) -> "Projection":
        return project(self, np.asarray(xy, float))

    def frenet(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Road coordinates ``(s, l)``, each ``(...)``, of world points ``xy (..., 2)``."""
        p = self.project(xy)
        return p.s, p.l

    def _at(self, s: np.ndarray, values: np.ndarray) -> np.ndarray:
        return np.interp(np.asarray(s, float), self.s, values)

    def heading_at(self, s: np.ndarray) -> np.ndarray:
        """Centreline heading [rad] at arc length ``s`` (the end values beyond the ends)."""
        return self._at(s, self.heading)

    def curvature_at(self, s: np.ndarray) -> np.ndarray:
        return self._at(s, self.curvature)

    def edges_at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The left and right edges' lateral offsets [m] at ``s``."""
        return self._at(s, self.left), self._at(s, self.right)

    def position(self, s: np.ndarray, lat: np.ndarray) -> np.ndarray:
        """World position ``(..., 2)`` of road coordinates ``s``, ``lat`` (broadcastable): on the polyline's chords,
        extended straight past the ends."""
        s, lat = np.broadcast_arrays(np.asarray(s, float), np.asarray(lat, float))
        i = np.clip(np.searchsorted(self.s, s, side="right") - 1, 0, len(self.s) - 2)
        a, b = self.xy[i], self.xy[i + 1]
        t = (s - self.s[i]) / (self.s[i + 1] - self.s[i])
        d = b - a
        unit = d / np.linalg.norm(d, axis=-1, keepdims=True)
        normal = np.stack([-unit[..., 1], unit[..., 0]], axis=-1)
        return a + t[..., None] * d + lat[..., None] * normal

    def edge_distance(self, states: np.ndarray, length: float, width: float) -> np.ndarray:
        """Least signed distance [m] of the four body corners to the drivable area's edges, ``(...)`` for states
        ``(..., >=3)`` ``[x, y, heading, ..]``: > 0 inside. Exact for the rectangle, up to the polyline."""
        states = np.asarray(states, float)
        return corner_edge_margin(self.project(body_corners(states[..., :2], states[..., 2], length, width)))


class Projection(NamedTuple):
    """Where points lie on a route, each ``(...)``: arc length, lateral offset (> 0 right), and the route's
    heading, curvature and edges there."""

    s: np.ndarray
    l: np.ndarray  # noqa: E741 (the road's lateral coordinate, named as everywhere in the project)
    heading: np.ndarray
    curvature: np.ndarray
    left: np.ndarray
    right: np.ndarray


def corner_edge_margin(corners: Projection) -> np.ndarray:
    """Least signed distance [m] ``(...)`` of projected body corners ``(..., 4)`` to the edges: > 0 inside."""
    return np.minimum(corners.right - corners.l, corners.l - corners.left).min(axis=-1)


COARSE = 8  # every COARSE-th point first, then the 2 COARSE points around the nearest: (P / 8 + 16) distances


def _nearest_point(xp, points, xy):
    """Index ``(...)`` of the nearest of ``points (P, 2)`` to each of ``xy (..., 2)``: coarse to fine, so a point
    costs about P / 8 + 16 distances instead of P (the particles' projection is a plan's largest road cost). Exact
    for points within a few metres of a route that bends no sharper than about a COARSE-point arc per COARSE points
    (every road here: 8 m at 1 m spacing against radii >= 9 m)."""
    count = points.shape[0]
    if count <= 4 * COARSE:
        return xp.argmin(((xy[..., None, :] - points) ** 2).sum(-1), axis=-1)
    coarse = xp.argmin(((xy[..., None, :] - points[::COARSE]) ** 2).sum(-1), axis=-1) * COARSE
    near = xp.clip(coarse[..., None] + xp.arange(-COARSE, COARSE + 1), 0, count - 1)   # (..., 2 COARSE + 1)
    best = xp.argmin(((xy[..., None, :] - points[near]) ** 2).sum(-1), axis=-1)
    return xp.take_along_axis(near, best[..., None], axis=-1)[..., 0]


def project(route, xy) -> Projection:
    """Nearest-segment projection of points ``xy (..., 2)`` on a route (a :class:`Route`, or the planners' traced
    copy with the same fields): the nearest of the ``P`` points (:func:`_nearest_point`), then the nearer of the two
    segments that meet there. The first segment extends backwards, the last
    forwards. numpy or JAX, the module following the inputs."""
    xp = array_module(xy, route.xy)
    n = route.xy.shape[0] - 1                                 # segments
    j = _nearest_point(xp, route.xy, xy)
    i = xp.clip(xp.stack([j - 1, j], axis=-1), 0, n - 1)        # (..., 2) the segments that meet there
    a, d = route.xy[i], route.xy[i + 1] - route.xy[i]          # (..., 2, 2)
    length2 = (d**2).sum(-1)                                  # (..., 2)
    rel = xy[..., None, :] - a
    t = (rel * d).sum(-1) / length2                           # (..., 2)
    lo, hi = xp.where(i == 0, -xp.inf, 0.0), xp.where(i == n - 1, xp.inf, 1.0)
    off = rel - xp.clip(t, lo, hi)[..., None] * d
    k = xp.argmin((off**2).sum(-1), axis=-1)[..., None]        # (..., 1) the nearer of the two
    i = xp.take_along_axis(i, k, axis=-1)[..., 0]
    # Its t unclipped: a point outside a bend, in the wedge between two segments, lies just past the end of both.
    t_i = xp.take_along_axis(t, k, axis=-1)[..., 0]
    length = xp.sqrt(xp.take_along_axis(length2, k, axis=-1)[..., 0])
    rel_i = xp.take_along_axis(rel, k[..., None], axis=-2)[..., 0, :]
    d_i = xp.take_along_axis(d, k[..., None], axis=-2)[..., 0, :]
    lat = (d_i[..., 0] * rel_i[..., 1] - d_i[..., 1] * rel_i[..., 0]) / length

    def lerp(values, t):
        return values[i] + t * (values[i + 1] - values[i])

    # The chord's normal is not the road's: on a curve the road's normal turns by dh over the segment, so a point
    # off the centreline projects onto the chord shifted by about l (t - 1/2) dh. Undo it (s to 0.1 mm on the
    # paper's curves at 1 m spacing, 5 m off the centre; uncorrected, 1.5 cm).
    dh = route.heading[i + 1] - route.heading[i]
    t_i = t_i + lat * (xp.clip(t_i, 0.0, 1.0) - 0.5) * dh / length
    inner = xp.clip(t_i, 0.0, 1.0)  # past either end the route runs straight: heading, curvature, edges held
    return Projection(lerp(route.s, t_i), lat, lerp(route.heading, inner), lerp(route.curvature, inner),
                      lerp(route.left, inner), lerp(route.right, inner))


# --- the closed form's road frame as functions of its numbers ----------------------------------------------------
# RoadGeometry's queries (numpy or JAX: the array module follows the inputs). The planners no longer call them (they
# project on a Route); they remain the paper road's exact description and the tests' oracle for the polyline.
def array_module(*arrays):
    """``jax.numpy`` if any of ``arrays`` is a JAX array (a tracer included), else ``numpy``: what the shared
    numpy-or-JAX functions (here, :mod:`bimp.envs.scene`, :mod:`bimp.planners.problem`) compute with. JAX is
    imported only when a JAX array is passed, so the env never loads it."""
    for a in arrays:
        if type(a).__module__.startswith("jax"):
            import jax.numpy as jnp

            return jnp
    return np


def heading_at(s, straight_in, radius, arc_angle):
    """Centreline heading [rad] at arc length ``s (...)`` of the road straight_in + arc + straight."""
    xp = array_module(s, straight_in, radius, arc_angle)
    turn = xp.where(arc_angle >= 0, 1.0, -1.0)
    return turn * xp.clip((s - straight_in) / radius, 0.0, xp.abs(arc_angle))


def curvature_at(s, straight_in, radius, arc_angle):
    """Signed centreline curvature [1/m] at ``s (...)``, > 0 turning right, 0 on the straights."""
    xp = array_module(s, straight_in, radius, arc_angle)
    arc_length = radius * xp.abs(arc_angle)
    on_arc = (s >= straight_in) & (s <= straight_in + arc_length) & (arc_length > 0)
    return xp.where(on_arc, xp.where(arc_angle >= 0, 1.0, -1.0) / radius, 0.0)


def to_frenet(xy, straight_in, radius, arc_angle):
    """Road coordinates ``(s, l)``, each ``(...)``, of world points ``xy (..., 2)``.

    Before the arc: the first straight (extended backwards); on the arc: angle about its centre; past the arc's end
    (projected on the last straight's direction): the last straight. Straight road (``arc_angle = 0``): ``(x, y)``.
    """
    xp = array_module(xy, straight_in, radius, arc_angle)
    x, y = xy[..., 0], xy[..., 1]
    turn = xp.where(arc_angle >= 0, 1.0, -1.0)
    angle = xp.abs(arc_angle)
    arc_length = radius * angle
    dx, dy = x - straight_in, y - turn * radius  # from the arc's centre
    phi = xp.arctan2(dx, -turn * dy)
    on_arc = (phi >= 0.0) & (arc_length > 0)
    s = xp.where(on_arc, straight_in + radius * phi, x)
    lat = xp.where(on_arc, turn * (radius - xp.hypot(dx, dy)), y)
    h_end = turn * angle
    rx, ry = dx - radius * xp.sin(angle), dy + turn * radius * xp.cos(angle)  # from the arc's end
    s_out = straight_in + arc_length + rx * xp.cos(h_end) + ry * xp.sin(h_end)
    l_out = -rx * xp.sin(h_end) + ry * xp.cos(h_end)
    past = s_out >= straight_in + arc_length
    return xp.where(past, s_out, s), xp.where(past, l_out, lat)


def corner_edge_distance(x, length, width, straight_in, radius, arc_angle, half_width):
    """Least signed distance [m] of the four body corners to the road edge, ``(...)`` for states ``x (..., >=3)``
    ``[x, y, heading, ..]`` of ``length`` x ``width`` vehicles: > 0 on the road. Exact for the rectangle; numpy or
    JAX (the env's ``info`` and the planning problem both read it)."""
    _, lat = to_frenet(body_corners(x[..., :2], x[..., 2], length, width), straight_in, radius, arc_angle)
    return (half_width - array_module(lat).abs(lat)).min(axis=-1)


def wrap_angle(angle):
    """``angle`` in [-pi, pi), numpy or JAX: a heading error on a road that turns a full circle (a roundabout)
    stays small."""
    return (angle + np.pi) % (2 * np.pi) - np.pi


def rect_gap(xy1, heading1, xy2, heading2, length: float, width: float) -> np.ndarray:
    """Exact signed distance [m] between two vehicles' footprints, ``length`` x ``width`` rectangles centred at
    ``xy (..., 2)`` and turned by ``heading (...)`` (any broadcastable leading shapes), as highway-env draws them.

    Positive: the Euclidean distance between the rectangles (the least vertex-to-edge distance, exact for convex
    polygons). Zero when they touch. Negative when they overlap: minus the penetration depth, the least
    translation that separates them (for convex polygons it lies along one of the four edge normals, so it is
    minus the least interval overlap of the separating-axis test). So ``rect_gap <= 0`` exactly when the
    footprints share a point.
    """
    xy1, xy2 = np.asarray(xy1, float), np.asarray(xy2, float)
    h1, h2 = np.asarray(heading1, float), np.asarray(heading2, float)
    shape = np.broadcast_shapes(xy1.shape[:-1], xy2.shape[:-1], h1.shape, h2.shape)
    h1, h2 = np.broadcast_to(h1, shape), np.broadcast_to(h2, shape)
    cyc = [0, 1, 3, 2]  # body_corners' order -> around the rectangle
    a = body_corners(np.broadcast_to(xy1, shape + (2,)), h1, length, width)[..., cyc, :]
    b = body_corners(np.broadcast_to(xy2, shape + (2,)), h2, length, width)[..., cyc, :]
    # Separating-axis test on the four edge normals: per axis, the signed gap between the projected intervals.
    axes = np.stack([np.stack([np.cos(h), np.sin(h)], -1) for h in (h1, h2)]
                    + [np.stack([-np.sin(h), np.cos(h)], -1) for h in (h1, h2)], -2)
    pa, pb = np.einsum("...ck,...ak->...ac", a, axes), np.einsum("...ck,...ak->...ac", b, axes)
    sep = np.maximum(pb.min(-1) - pa.max(-1), pa.min(-1) - pb.max(-1)).max(-1)
    return np.where(sep > 0, np.minimum(_vertex_edge_distance(a, b), _vertex_edge_distance(b, a)), sep)


def _vertex_edge_distance(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Least distance ``(...)`` from the vertices of polygon ``p (..., n, 2)`` to the edges of ``q (..., m, 2)``."""
    start, edge = q, np.roll(q, -1, axis=-2) - q                     # (..., m, 2)
    rel = p[..., :, None, :] - start[..., None, :, :]                 # (..., n, m, 2)
    t = np.clip(np.sum(rel * edge[..., None, :, :], -1) / np.sum(edge**2, -1)[..., None, :], 0.0, 1.0)
    return np.linalg.norm(rel - t[..., None] * edge[..., None, :, :], axis=-1).min(axis=(-2, -1))


def body_corners(xy: np.ndarray, heading: np.ndarray, length: float, width: float) -> np.ndarray:
    """World positions ``(..., 4, 2)`` of the body corners of vehicles at ``xy (..., 2)``, ``heading (...)``."""
    xp = array_module(xy, heading, length)
    c, s = xp.cos(heading)[..., None], xp.sin(heading)[..., None]
    fwd = np.array([1, 1, -1, -1]) * 0.5 * length
    side = np.array([1, -1, 1, -1]) * 0.5 * width
    return xp.stack([xy[..., None, 0] + fwd * c - side * s, xy[..., None, 1] + fwd * s + side * c], axis=-1)
