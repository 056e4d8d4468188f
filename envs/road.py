"""Road geometry shared by the simulator and the planners.

The road is a centreline made of a straight, a circular arc and a straight (the paper's curved highway;
an arc angle of 0 gives a straight road). Points are described in road (Frenet) coordinates ``(s, l)``:
``s`` is the arc length along the centreline, ``l`` the lateral offset, positive to the *right* of the
direction of travel (highway-env's convention: +y at heading 0, the bottom of the rendered image).
Lane ``i`` of ``n`` has its centre at ``l = (i - (n - 1) / 2) * lane_width``, so lane 0 is the left lane and
the road edges are at ``l = +-n * lane_width / 2``.

Every query is vectorized over leading dimensions so a planner can ask for all particles at once.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

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


# --- the road frame as functions of the geometry's numbers -----------------------------------------------------
# One definition for the env (numpy, through RoadGeometry) and the planners (jax.numpy, with the geometry as
# traced parameters, so a redrawn road does not recompile): the array module follows the inputs.
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
