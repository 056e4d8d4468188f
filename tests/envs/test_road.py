"""The exact footprint gap between two turned rectangles (``bimp.envs.road.rect_gap``, used by ``Scene.ov_gaps``)."""

import numpy as np
import pytest
from highway_env import utils

from bimp.envs.road import RoadGeometry, body_corners, rect_gap
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
