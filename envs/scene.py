"""What a planner may know beside the observation: the static scene description an env publishes.

``env.unwrapped.scene`` is a frozen :class:`Scene`, rebuilt at every ``reset`` (the road is randomized).
It also owns the observation layout and the planning-constraint functions (paper eq. 2-5) so that the
env's ``info`` and the planners' barriers compute the very same quantities.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bimp.envs.road import RoadGeometry, corner_edge_distance, rect_gap

EGO_FIELDS = ("x", "y", "heading", "speed")
OV_FIELDS = ("present", "x", "y", "heading", "speed", "acceleration")
REF_FIELDS = ("speed", "acceleration", "lane_offset")


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
    """

    accel: tuple[float, float] = (-7.0, 3.0)
    steer: float = 0.05
    accel_rate: float = 1.0
    steer_rate: float = 0.005
    d_min: float = 1.0
    edge_margin: float = 0.0

    def input_violation(self, u: np.ndarray) -> np.ndarray:
        """Per-row max of the input-bound constraint values ``phi(u) (N,)`` for ``u (N, 2)``; <= 0 is feasible."""
        u = np.atleast_2d(u)
        return np.max(
            np.stack([self.accel[0] - u[:, 0], u[:, 0] - self.accel[1], np.abs(u[:, 1]) - self.steer], -1), -1
        )

    def rate_violation(self, du: np.ndarray) -> np.ndarray:
        """Per-row max of the rate constraint values ``(N,)`` for ``du (N, 2)``; <= 0 is feasible."""
        du = np.atleast_2d(du)
        return np.maximum(np.abs(du[:, 0]) - self.accel_rate, np.abs(du[:, 1]) - self.steer_rate)


@dataclass(frozen=True)
class Scene:
    """Static description of one episode's scene.

    ``actuator_accel`` / ``actuator_steer``: physical ranges that the normalized action [-1, 1] maps onto.
    ``n_obstacles``: fixed number of OV slots in the observation (absent ones are masked, ``present = 0``).
    """

    road: RoadGeometry
    bounds: Bounds
    dt: float
    vehicle_length: float
    vehicle_width: float
    actuator_accel: tuple[float, float]
    actuator_steer: tuple[float, float]
    n_obstacles: int

    # --- observation layout --------------------------------------------------------------------------
    @property
    def obs_dim(self) -> int:
        return len(EGO_FIELDS) + 2 + self.n_obstacles * len(OV_FIELDS) + len(REF_FIELDS)

    def split_obs(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``obs (obs_dim,)`` -> ego ``[x, y, heading, speed] (4,)``, previous input ``[a, delta] (2,)``,
        OVs ``(n_obstacles, 6)`` with columns :data:`OV_FIELDS`, reference ``[v_ref, a_ref, l_ref] (3,)``."""
        obs = np.asarray(obs, dtype=float)
        k = 6 + self.n_obstacles * len(OV_FIELDS)
        return obs[:4], obs[4:6], obs[6:k].reshape(self.n_obstacles, len(OV_FIELDS)), obs[k:]

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
        """Least signed distance [m] of the body corners to the road edge, ``(...)`` for ``states (..., 4)``."""
        r = self.road
        return corner_edge_distance(np.asarray(states, float), self.vehicle_length, self.vehicle_width,
                                    r.straight_in, r.radius, r.arc_angle, r.half_width)

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
