"""Feasibility oracle: the plan that brakes at the planning bounds, simulated as highway-env steps it.

Every scenario's documented ranges must leave a safe plan inside the planning bounds (issue 27: "an oracle in the
tests shows it on at least 1000 draws"). For the longitudinal cases that plan is braking in the EV's lane: from its
last input (0 at reset) the EV ramps to ``a_min`` by the rate bound, one step after it sees the reason to. The tests
run it over the drawn instances (``tests/envs/test_feasibility.py``, ``tests/envs/test_suite_stalled_vehicle.py``),
and a family refuses ranges whose worst case it fails (:mod:`bimp.envs.suite`), so the oracle lives here, in the
package, where both read it.

The motion is highway-env's kinematic ``Vehicle.step`` along a straight lane: position advanced with the step's
starting speed, then speed by the acceleration, clamped at 0 (bimp's EV and highway-env's braking vehicles never
reverse). Pure numpy: no highway-env, no env.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from bimp.envs.scene import DT, VEHICLE_LENGTH, Bounds

NEVER = np.inf  # an ``onset`` for an OV that never brakes (a stalled vehicle, a steady leader)


def lag_gain(lag: ArrayLike, dt: float = DT) -> np.ndarray:
    """The share ``1 - exp(-dt / lag)`` of the gap between command and achieved acceleration closed in one step of
    ``dt`` [s] by a first-order lag of time constant ``lag`` [s] (1 for ``lag`` 0: no lag). Arrays broadcast."""
    lag = np.asarray(lag, float)
    with np.errstate(divide="ignore"):
        return 1.0 - np.exp(-dt / lag)


def braking(ev, gap, v_ov, onset, decel, dt: float = DT, length: float = VEHICLE_LENGTH, steps: int = 200,
            react: bool = True, bounds: Bounds | None = None, duration=NEVER, a0=0.0, lag=0.0,
            grip=1.0) -> tuple[np.ndarray, np.ndarray]:
    """The EV braking at the planning bounds behind an OV in its lane: its least footprint gap [m] to the OV
    ``(...)`` and the distance [m] it travels ``(...)`` (to its stop, where ``steps`` cover it).

    The OV (centre ``gap`` [m] ahead, speed ``v_ov`` [m/s]) brakes at ``decel`` [m/s^2, a magnitude] from ``onset``
    [s] until it stands, or for ``duration`` [s] (the steps whose clock is in ``[onset, onset + duration)``) and
    then holds its speed (:data:`NEVER` onset: it holds its speed; ``v_ov`` 0: it stands throughout). The EV
    (speed ``ev`` [m/s], last input ``a0`` [m/s^2], 0 by default) sees the OV's deceleration in the observation
    after the first braking step (``react``) or from the start (``react=False``: it brakes from its first step), and
    from then ramps its command from ``a0`` to ``bounds.accel[0]`` by ``bounds.accel_rate`` per step (``bounds``:
    the paper's :class:`bimp.envs.scene.Bounds` by default). The acceleration it achieves follows the command
    through a first-order lag of ``lag`` [s] (:func:`lag_gain`), scaled by ``grip`` (the suite's paper-noisy EV);
    ``lag`` 0 and ``grip`` 1 (the defaults): the command itself. ``length`` [m]: both vehicles' length, so the
    footprint gap is the centre gap less it. ``steps`` of ``dt`` [s] must cover the stop (200 x 0.1 s: from
    40 m/s at 7 m/s^2 the EV stands within 7 s; a lag and less grip take longer, paper-noisy passes 250); the loop
    ends early once every EV stands. Arrays broadcast."""
    b = Bounds() if bounds is None else bounds
    ev, gap, v_ov, onset, decel, duration, a0, lag, grip = np.broadcast_arrays(
        *(np.asarray(a, float) for a in (ev, gap, v_ov, onset, decel, duration, a0, lag, grip)))
    alpha = lag_gain(lag, dt)
    s_e, v_e, a_cmd, a_e = np.zeros(ev.shape), ev.copy(), a0.copy(), grip * a0
    s_o, v_o = gap.copy(), v_ov.copy()
    seen = np.zeros(ev.shape, bool) if react else np.ones(ev.shape, bool)
    least = np.full(ev.shape, np.inf)
    clock = 0.0
    for _ in range(steps):
        ov_brakes = (clock >= onset) & (clock < onset + duration) & (v_o > 0)  # NEVER + anything: never ends
        a_o = np.where(ov_brakes, -decel, 0.0)
        a_cmd = np.where(seen, np.maximum(a_cmd - b.accel_rate, b.accel[0]), a_cmd)
        a_e = a_e + alpha * (grip * a_cmd - a_e)
        s_e, v_e = s_e + v_e * dt, np.maximum(v_e + a_e * dt, 0.0)
        s_o, v_o = s_o + v_o * dt, np.maximum(v_o + a_o * dt, 0.0)
        clock += dt
        seen |= ov_brakes
        least = np.minimum(least, s_o - s_e - length)
        if not v_e.any():  # every EV stands: the gaps only grow from here (no OV reverses)
            break
    return least, s_e


def brake_at_the_bounds(ev, gap, v_ov, onset, decel, dt: float = DT, length: float = VEHICLE_LENGTH,
                        steps: int = 200, react: bool = True, bounds: Bounds | None = None,
                        duration=NEVER, a0=0.0, lag=0.0, grip=1.0) -> np.ndarray:
    """Least footprint gap [m] ``(...)`` to the OV ahead in the EV's lane when the EV brakes at the planning bounds:
    :func:`braking`'s first value, its arguments the same."""
    return braking(ev, gap, v_ov, onset, decel, dt, length, steps, react, bounds, duration, a0, lag, grip)[0]


def stop_behind(ev: ArrayLike, gap: ArrayLike, bounds: Bounds | None = None) -> np.ndarray:
    """Least footprint gap [m] ``(...)`` to a vehicle standing ``gap`` [m] (centre to centre) ahead in the EV's lane
    when the EV (speed ``ev`` [m/s], last input 0) brakes at the bounds from its first step: the stop that a
    stalled vehicle always leaves. :func:`brake_at_the_bounds` with an OV at 0 that it sees from the start."""
    return brake_at_the_bounds(ev, gap, 0.0, NEVER, 0.0, react=False, bounds=bounds)
