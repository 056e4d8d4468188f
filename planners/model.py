"""The vehicle models of :mod:`bimp.planners.dynamics` as pure JAX functions of parameter pytrees (paper eq. 1).

Loading stays in torch (:mod:`bimp.planners.dynamics`; training in :mod:`bimp.planners.dynamics_train`):
:func:`model_params` turns the shipped MLP (or any weights file written by ``bimp train-dynamics``), or the exact
bicycle model, into numbers that :func:`step` evaluates inside the compiled planner. A test pins ``step`` to the
torch forward pass.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from bimp.planners.dynamics import BicycleModel, model_from_name


class MLPParams(NamedTuple):
    """The MLP with its input and output normalization folded into the first and last layers (float32), and the
    hard limits applied around it: actuator ranges ``accel (2,)``, ``steer (2,)``, highway-env's speed cap."""

    w1: np.ndarray
    b1: np.ndarray
    w2: np.ndarray
    b2: np.ndarray
    w3: np.ndarray
    b3: np.ndarray
    max_speed: float
    accel: np.ndarray
    steer: np.ndarray


class BicycleParams(NamedTuple):
    """The exact kinematic bicycle of the env: ``dt`` [s], ``length`` [m], speed cap and actuator ranges."""

    dt: float
    length: float
    max_speed: float
    accel: np.ndarray
    steer: np.ndarray


def model_params(name: str, steer_bound: float = 0.0) -> MLPParams | BicycleParams:
    """Parameters of the model a config's ``dynamics`` names (``"mlp"``, ``"bicycle"`` or a weights file) on a road
    with planning steering bound ``steer_bound`` [rad] (:func:`bimp.planners.dynamics.model_from_name`)."""
    model = model_from_name(name, steer_bound)
    if isinstance(model, BicycleModel):
        return BicycleParams(float(model.dt), float(model.length), float(model.max_speed),
                             np.array(model.accel_range, float), np.array(model.steer_range, float))
    (w1, w2, w3), (b1, b2, b3) = model._w, model._b
    return MLPParams(w1, b1, w2, b2, w3, b3, float(model.max_speed), np.array(model.accel_range, np.float32),
                     np.array(model.steer_range, np.float32))


def step(model: MLPParams | BicycleParams, x: jnp.ndarray, u: jnp.ndarray) -> jnp.ndarray:
    """Next states ``(N, 4)`` from states ``x (N, 4)`` and physical inputs ``u (N, 2)``: inputs clipped to the
    actuator ranges, highway-env's acceleration cap above ``max_speed``, next speed clamped at 0."""
    v = x[:, 3]
    a = jnp.clip(u[:, 0], model.accel[0], model.accel[1])
    delta = jnp.clip(u[:, 1], model.steer[0], model.steer[1])
    a = jnp.where(v > model.max_speed, jnp.minimum(a, model.max_speed - v), a)
    h = x[:, 2]
    if isinstance(model, BicycleParams):
        beta = jnp.arctan(0.5 * jnp.tan(delta))
        return jnp.stack([x[:, 0] + v * jnp.cos(h + beta) * model.dt, x[:, 1] + v * jnp.sin(h + beta) * model.dt,
                          h + v * jnp.sin(beta) / (model.length / 2) * model.dt,
                          jnp.maximum(v + a * model.dt, 0.0)], axis=1)
    f = jnp.stack([v, a, delta], axis=1).astype(model.w1.dtype)
    hidden = jnp.tanh(jnp.tanh(f @ model.w1 + model.b1) @ model.w2 + model.b2)
    d = (hidden @ model.w3 + model.b3).astype(x.dtype)  # body-frame [d_lon, d_lat, d_heading, d_speed]
    c, s = jnp.cos(h), jnp.sin(h)
    return jnp.stack([x[:, 0] + c * d[:, 0] - s * d[:, 1], x[:, 1] + s * d[:, 0] + c * d[:, 1], h + d[:, 2],
                      jnp.maximum(v + d[:, 3], 0.0)], axis=1)


__all__ = ["BicycleParams", "MLPParams", "model_params", "step"]
