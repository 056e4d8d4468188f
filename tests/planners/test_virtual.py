import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401  (registers the envs)
from planners.virtual import BarrierShape, measure, n_measurements, predict_obstacles, reference_profile


@pytest.fixture
def scene():
    env = gym.make("bimp/EmergencyBrake-v0")
    env.reset(seed=0)
    return env.unwrapped.scene


def test_obstacles_brake_to_a_stop_and_stay_there(scene):
    ovs = np.array([[1.0, 50.0, 2.0, 0.0, 10.0, -5.0], [1.0, 80.0, -2.0, 0.0, 20.0, 0.0]])
    s, lat, v, a, present = predict_obstacles(scene, ovs, horizon=30)
    assert s.shape == v.shape == a.shape == lat.shape == (31, 2) and present.all()
    np.testing.assert_allclose(v[:, 0], np.maximum(10.0 - 5.0 * 0.1 * np.arange(31), 0.0))
    np.testing.assert_allclose(s[-1, 0], 50.0 + 10.0**2 / (2 * 5.0))  # stopped after 2 s, 10 m on
    assert np.all(a[20:, 0] == 0.0) and np.all(a[:20, 0] == -5.0)
    np.testing.assert_allclose(s[:, 1], 80.0 + 20.0 * 0.1 * np.arange(31))
    np.testing.assert_allclose(lat, [[2.0, -2.0]] * 31)


def test_reference_profile_never_negative(scene):
    v, a = reference_profile(scene, np.array([2.0, -5.0, 2.0]), horizon=10)
    np.testing.assert_allclose(v, np.maximum(2.0 - 0.5 * np.arange(11), 0.0))
    assert np.all(a[v == 0] == 0.0) and a[0] == -5.0


def test_measurement_reads_zero_on_the_reference_and_flags_each_constraint(scene):
    shape = BarrierShape()
    far = (np.array([500.0, 500.0]), np.array([2.0, -2.0]), np.array([20.0, 20.0]), np.zeros(2),
           np.ones(2, bool))
    x = np.array([[10.0, 2.0, 0.0, 20.0]])
    zero_u = np.zeros((1, 2))
    h = measure(scene, shape, x, zero_u, zero_u, zero_u, np.zeros(2), 2.0, 20.0, 0.0, far)
    assert h.shape == (1, n_measurements(2))
    np.testing.assert_allclose(h[0, :5], 0.0, atol=1e-12)
    assert np.all(h[0, 5:] < 1e-3)

    near = (np.array([14.0, 500.0]), np.array([2.0, -2.0]), np.array([20.0, 20.0]), np.zeros(2), np.ones(2, bool))
    h_near = measure(scene, shape, x, zero_u, zero_u, zero_u, np.zeros(2), 2.0, 20.0, 0.0, near)
    assert h_near[0, 5] > 1.0 and h_near[0, 6] < 1e-3  # OV1 right ahead in the lane; OV2 far

    off_edge = np.array([[10.0, 3.9, 0.0, 20.0]])
    bad_u = np.array([[-9.0, 0.2]])
    h_bad = measure(scene, shape, off_edge, bad_u, bad_u, bad_u, np.zeros(2), 2.0, 20.0, 0.0, far)
    assert np.all(h_bad[0, 7:] > 1.0)  # edge, both bounds, both rates, and the four first-control barriers
