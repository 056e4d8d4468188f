"""Road geometry: the exact footprint gap between two turned rectangles (``rect_gap``, used by ``Scene.ov_gaps``)
and the general road (``Route``: a polyline the planners project on)."""

import numpy as np
import pytest
from highway_env import utils

from bimp.envs.road import RoadGeometry, Route, body_corners, corner_edge_distance, project, rect_gap
from bimp.envs.scene import Bounds, Scene

L, W = 5.0, 2.0


def test_rect_gap_is_the_exact_signed_rectangle_distance_on_hand_cases():
    cases = [  # (xy2, heading2, expected) with the first 5 x 2 rectangle at the origin, heading 0
        ([10.0, 0.0], 0.0, 5.0), ([5.0, 0.0], 0.0, 0.0), ([4.0, 0.0], 0.0, -1.0), ([8.0, 6.0], 0.0, 5.0),
        ([0.0, 3.0], np.pi / 2, -0.5), ([0.0, 1.5], 0.0, -0.5), ([0.0, 0.0], 0.0, -2.0),
        # turned by 0.1 rad, 10 m ahead: its nearest corner is at x = 10 - 2.5 cos 0.1 - sin 0.1
        ([10.0, 0.0], 0.1, 10.0 - 2.5 * np.cos(0.1) - np.sin(0.1) - 2.5),
    ]
    for xy2, h2, expected in cases:
        assert rect_gap([0.0, 0.0], 0.0, xy2, h2, L, W) == pytest.approx(expected, abs=1e-12), (xy2, h2)
        assert rect_gap(xy2, h2, [0.0, 0.0], 0.0, L, W) == pytest.approx(expected, abs=1e-12), (xy2, h2)
    # A corner of a 2 x 2 square turned by 45 degrees (sqrt 2 from its centre) 0.3 m from the other's edge:
    # road-aligned boxes would say 0.3 - (sqrt 2 - 1).
    gap = rect_gap([0.0, 0.0], 0.0, [1.0 + np.sqrt(2) + 0.3, 0.0], np.pi / 4, 2.0, 2.0)
    assert gap == pytest.approx(0.3, abs=1e-12)


def intersect(a, b) -> bool:
    """highway-env's separating-axis test on two rectangles given by their corners in order."""
    closed = [np.vstack([p, p[:1]]) for p in (a, b)]
    return bool(utils.are_polygons_intersecting(*closed, np.zeros(2), np.zeros(2))[0])


def test_rect_gap_matches_brute_force_distance_and_highway_env_overlap():
    rng = np.random.default_rng(0)
    n = 150
    xy = rng.uniform([-9.0, -4.0], [9.0, 4.0], size=(n, 2))
    heading = rng.uniform(-np.pi, np.pi, size=n)
    gaps = rect_gap(np.zeros(2), 0.3, xy, heading, L, W)
    assert gaps.shape == (n,)
    a = body_corners(np.zeros(2), np.array(0.3), L, W)[[0, 1, 3, 2]]
    t = np.linspace(0.0, 1.0, 101)[:, None]
    boundary_a = np.concatenate([p + t * (q - p) for p, q in zip(a, np.roll(a, -1, 0))])
    checked = 0
    for k in range(n):
        b = body_corners(xy[k], heading[k], L, W)[[0, 1, 3, 2]]
        assert (gaps[k] <= 0) == intersect(a, b), k
        if gaps[k] > 0:
            boundary_b = np.concatenate([p + t * (q - p) for p, q in zip(b, np.roll(b, -1, 0))])
            brute = np.linalg.norm(boundary_a[:, None] - boundary_b[None], axis=-1).min()
            assert gaps[k] <= brute + 1e-9 and gaps[k] == pytest.approx(brute, abs=0.05), k
        else:
            # Minus the penetration depth: the least translation of one rectangle that separates them. Shorter
            # moves in any direction leave them overlapping; a move just longer along one edge normal separates.
            depth = -gaps[k]
            dirs = [[np.cos(t), np.sin(t)] for t in np.linspace(0, 2 * np.pi, 37)[:-1]]
            normals = [[np.cos(h), np.sin(h)] for h in (0.3, 0.3 + np.pi / 2, heading[k], heading[k] + np.pi / 2)]
            normals += [[-x, -y] for x, y in normals]
            assert all(intersect(a, b + (depth - 1e-6) * np.array(u)) for u in dirs), k
            assert not all(intersect(a, b + (depth + 1e-6) * np.array(u)) for u in normals), k
            checked += 1
    assert checked > 10


def test_penetration_depth_separates_exactly_along_the_best_axis():
    # Overlap of 0.7 m along x (least), 1.2 m along y: the depth is the least one.
    assert rect_gap([0, 0], 0.0, [4.3, 0.8], 0.0, L, W) == pytest.approx(-0.7)
    assert rect_gap([0, 0], 0.0, [4.3, 1.5], 0.0, L, W) == pytest.approx(-0.5)


def test_scene_ov_gaps_uses_the_ov_headings_and_masks_absent_ovs():
    scene = Scene(road=RoadGeometry(), bounds=Bounds(), dt=0.1, vehicle_length=L, vehicle_width=W,
                  actuator_accel=(-10.0, 10.0), actuator_steer=(-0.3, 0.3), n_obstacles=3)
    ego = np.array([0.0, 0.0, 0.0, 20.0])
    ovs = np.array([[1.0, 10.0, 0.0, 0.0, 20.0, 0.0],
                    [1.0, 10.0, 0.0, 0.1, 20.0, 0.0],
                    [0.0, 1.0, 0.0, 0.0, 0.0, 0.0]])
    gaps = scene.ov_gaps(ego, ovs)
    assert gaps[0] == pytest.approx(5.0) and gaps[1] == pytest.approx(rect_gap([0, 0], 0, [10, 0], 0.1, L, W))
    assert gaps[1] < gaps[0] and gaps[2] == np.inf


# --- the general road: a polyline route (issue 26) -------------------------------------------------------------
def _paper_roads(rng, n):
    """Roads of the paper's ranges (radius 180-220 m, arc +-50-70 degrees, either way)."""
    for _ in range(n):
        sign = rng.choice([-1.0, 1.0])
        yield RoadGeometry(straight_in=100.0, radius=rng.uniform(180, 220),
                           arc_angle=sign * np.deg2rad(rng.uniform(50, 70)), straight_out=300.0)


def test_the_paper_road_as_a_polyline_gives_its_closed_form_frenet_and_edges_to_1_mm():
    """The planners' road (a window of the env's route, P points every 1 m, the problem's defaults) against the
    closed form it was sampled from, on random states near the road in the window: s, l and the corner edge
    distance within 1 mm; within 3 mm on the segments across a junction of straight and arc, where the closed form's
    curvature jumps (linear in s between points, the polyline's curvature cannot jump there: 2 mm at 6 m off
    the centre)."""
    from bimp.planners.problem import ProblemConfig, frenet, road_window

    rng = np.random.default_rng(0)
    config = ProblemConfig()
    for geometry in _paper_roads(rng, 6):
        route = geometry.route()
        s_ev = rng.uniform(0.0, geometry.length - 150.0)
        road = road_window(route, geometry.position(s_ev, 2.0), config)
        s = rng.uniform(s_ev - 15.0, s_ev + 130.0, 400)
        lat = rng.uniform(-6.0, 6.0, 400)
        xy = geometry.position(s, lat)
        s_p, l_p = frenet(road, xy)
        junction = np.minimum(np.abs(s - geometry.straight_in), np.abs(s - geometry.straight_in
                                                                      - geometry.arc_length)) < 1.5
        tolerance = np.where(junction, 3e-3, 1e-3)
        assert np.all(np.abs(s_p - s) <= tolerance) and np.all(np.abs(l_p - lat) <= tolerance)
        heading = geometry.heading_at(s) + rng.uniform(-0.2, 0.2, 400)
        states = np.column_stack([xy, heading, np.full(400, 20.0)])
        window = Route(*road)
        closed = corner_edge_distance(states, 5.0, 2.0, geometry.straight_in, geometry.radius, geometry.arc_angle,
                                      geometry.half_width)
        assert np.all(np.abs(window.edge_distance(states, 5.0, 2.0) - closed) <= tolerance)


def test_project_in_jax_matches_numpy():
    import jax.numpy as jnp

    rng = np.random.default_rng(1)
    geometry = next(_paper_roads(rng, 1))
    route = geometry.route().window(80.0, 160, 1.0)
    xy = geometry.position(rng.uniform(60, 260, 200), rng.uniform(-5, 5, 200))
    expect = project(route, xy)
    traced = Route(*(jnp.asarray(getattr(route, k), jnp.float32)
                     for k in ("xy", "s", "heading", "curvature", "left", "right")))
    got = project(traced, jnp.asarray(xy, jnp.float32))
    for e, g in zip(expect, got):
        np.testing.assert_allclose(np.asarray(g), e, rtol=0, atol=2e-3 * (1 + np.abs(e).max() / 100))


def test_a_route_that_ends_is_padded_straight_never_nan():
    """A window past the end of the route (a road that ends mid-horizon) continues its last segment: finite, on the
    end heading, edges held."""
    route = Route.from_points(np.column_stack([np.arange(30.0), np.zeros(30)]), np.full(30, -4.0), np.full(30, 2.0))
    window = route.window(10.0, 100, 1.0)
    assert all(np.all(np.isfinite(getattr(window, k))) for k in ("xy", "s", "heading", "curvature", "left", "right"))
    np.testing.assert_allclose(window.xy[-1], [109.0, 0.0])
    np.testing.assert_allclose(window.heading, 0.0, atol=1e-12)
    p = window.project(np.array([[150.0, 1.0], [-20.0, -3.0]]))
    np.testing.assert_allclose(p.s, [150.0, -20.0])
    np.testing.assert_allclose(p.l, [1.0, -3.0])
    np.testing.assert_allclose(p.left, -4.0)
    np.testing.assert_allclose(p.right, 2.0)


def test_a_route_round_a_circle_keeps_its_heading_continuous_and_the_edges_asymmetric():
    """A full loop (a roundabout): the route's heading runs on past 2 pi, a point is projected on the nearest
    part, and the edges may differ left and right."""
    phi = np.linspace(0.0, 2.2 * np.pi, 700)
    xy = 20.0 * np.column_stack([np.sin(phi), 1 - np.cos(phi)])  # clockwise on screen: turning right, +y down
    route = Route.from_points(xy, np.full(700, -2.0), np.full(700, 6.0))
    assert route.heading[-1] > 2 * np.pi
    assert np.all(np.abs(route.curvature[5:-5] - 1 / 20.0) < 1e-3)
    p = route.project(np.array([[0.0, 3.0]]))  # 3 m inside the circle near its start: right of travel
    np.testing.assert_allclose(p.l, [3.0], atol=1e-2)
    d = route.edge_distance(np.array([[0.0, 0.0, 0.0, 10.0]]), 5.0, 2.0)
    assert 0.5 < d[0] < 1.2  # the left edge 2 m away, less the half width and the curve


def test_a_route_refuses_bad_arrays():
    with pytest.raises(ValueError, match="s must increase"):
        Route.from_points(np.zeros((3, 2)), np.zeros(3), np.ones(3))
    with pytest.raises(ValueError, match=">= 2 points"):
        Route(np.zeros((1, 2)), np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1))
    with pytest.raises(ValueError, match="finite"):
        Route.from_points(np.column_stack([np.arange(3.0), np.zeros(3)]), np.array([0, np.nan, 0]), np.ones(3))
