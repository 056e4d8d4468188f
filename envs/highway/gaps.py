"""A mandatory lane change planned through the gaps: the EV must reach a lane (exit-v0's exit lane) that highway-env's
MOBIL never heads for, and at exit-v0's density never finds a gap its own rule accepts (docs/highway-env.md).

:func:`plan_gaps` searches a space-time lattice for the earliest way into the needed lane: every ``step`` s the EV
picks an acceleration and whether to begin the next lane change towards the goal; a change takes ``change_steps``
steps, during which the EV holds both lanes. The other vehicles hold their lane and speed (exit-v0's traffic does
not change lanes). A lattice state is kept only while the EV keeps a safe gap to every vehicle in a lane it holds:
the footprint gap plus the distance that sheds the closing speed at ``brake`` m/s^2, both to the vehicle ahead and
to the one behind, at the start and the end of each step. No time headway: the EV crosses lanes slower than itself,
in front of their vehicles (with highway-env's driver executing the plan: with a 0.3 s headway it reached exit-v0's
exit lane on 8 of development seeds 0-11; with none, on 29 of 0-29, with no collision). States are merged on
(lane, change phase, speed to 2 m/s, position to 2 m), the cheapest kept, and of those at most ``per_group`` per
lane, phase and speed (to 4 m/s), the furthest ahead. A change once begun is not taken back.

The frame: parallel straight lanes numbered as highway-env numbers them (0 the leftmost), positions ``s`` [m] along
them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bimp.configs import ConfigError, check_fields


@dataclass(frozen=True)
class GapSearch:
    """The lattice: ``step`` [s] between decisions, ``change_steps`` per lane change, the ``accels`` [m/s^2] to pick
    from, ``top_speed`` [m/s], ``horizon`` [s] searched, the vehicles' ``length`` [m] (highway-env's 5 m), the safe
    gap (``gap`` [m], ``brake`` [m/s^2]: module doc) and ``per_group``: how many states are kept
    per lane, change phase and speed (to 4 m/s) at each step, those furthest ahead. ``lag`` [m/s^2 per lattice step
    of lane change left]: the cost of lateral progress put off, against braking's (so that of the ways that arrive
    first, the one that changes lanes early is taken, and a slower lane change than the lattice's still arrives).
    ``lookahead`` [s]: when the plan's lane is reported (:attr:`GapPlan.ahead`; the planners' horizon)."""

    step: float = 0.5
    change_steps: int = 4
    accels: tuple[float, ...] = (-4.0, -2.0, 0.0, 2.0)
    top_speed: float = 30.0
    horizon: float = 20.0
    length: float = 5.0
    gap: float = 2.0
    brake: float = 7.0
    per_group: int = 8
    lag: float = 0.5
    lookahead: float = 2.0

    def __post_init__(self) -> None:
        check_fields(self)
        for name in ("step", "top_speed", "horizon", "length", "brake"):
            if not getattr(self, name) > 0:
                raise ConfigError(name, "> 0", getattr(self, name))
        if not (self.lookahead >= 0 and abs(self.lookahead / self.step - round(self.lookahead / self.step)) < 1e-9):
            raise ConfigError("lookahead", "a whole number of steps >= 0 [s]", self.lookahead)
        if not self.lag >= 0:
            raise ConfigError("lag", ">= 0", self.lag)
        for name in ("change_steps", "per_group"):  # ints: check_fields refuses any other type
            if not getattr(self, name) >= 1:
                raise ConfigError(name, ">= 1", getattr(self, name))
        if not self.accels:
            raise ConfigError("accels", "at least one acceleration", self.accels)


@dataclass(frozen=True)
class GapPlan:
    """The plan's first step: ``accel`` [m/s^2] and ``change`` (begin, or go on with, the change to the next lane
    towards the goal), ``arrival`` [s]: when the EV is in the goal lane, and ``ahead``: where across the lanes the
    plan holds the EV :attr:`GapSearch.lookahead` s from now (lanes numbered as highway-env numbers them, a fraction
    of the way mid-change; the goal lane where it arrives sooner)."""

    accel: float
    change: bool
    arrival: float
    ahead: float


def plan_gaps(search: GapSearch, s0: float, v0: float, lane0: int, phase0: int, goal: int,
              window: tuple[float, float], others: np.ndarray) -> GapPlan | None:
    """The earliest way into lane ``goal`` within ``window`` (the first and last position [m] of the goal lane where
    the change may end), the cheapest among the earliest (braking, lane changes put off: :class:`GapSearch`); None
    where the lattice finds none within the horizon.

    ``s0`` [m], ``v0`` [m/s]: the EV's position and speed; ``lane0``: its lane (the one it is leaving, mid-change);
    ``phase0``: steps of the change from ``lane0`` towards ``goal`` already driven (0: none); ``others (N, 3)``:
    ``[lane, s m, v m/s]`` per other vehicle."""
    if phase0 and lane0 == goal:
        raise ValueError(f"a change of phase {phase0} in the goal lane {goal}: no change towards it is left")
    if not 0 <= phase0 < search.change_steps:
        raise ValueError(f"phase0 must be in [0, {search.change_steps}), got {phase0}")
    others = np.asarray(others, float).reshape(-1, 3)
    toward = int(np.sign(goal - lane0)) or 1
    accels = np.asarray(search.accels, float)
    n_a = len(accels)
    # states: lane, phase, s, v, cost (braking), first (the index of the first step's option: accel * 2 + change),
    # ahead (the state's place across the lanes at the lookahead: GapPlan.ahead)
    lane = np.array([lane0])
    phase = np.array([phase0])
    s, v, cost, first = np.array([s0], float), np.array([v0], float), np.zeros(1), np.full(1, -1)
    ahead = np.array([lane0 + toward * phase0 / search.change_steps], float)
    dt = search.step
    for k in range(int(round(search.horizon / dt))):
        t0 = k * dt
        # every state x every option (accel, change): (M * A * 2,)
        m = len(s)
        lane_, phase_, s_, v_, cost_, first_, ahead_ = (np.repeat(x, n_a * 2)
                                                        for x in (lane, phase, s, v, cost, first, ahead))
        a = np.tile(np.repeat(accels, 2), m)
        begin = np.tile(np.array([False, True]), m * n_a)
        ok = ~(begin & ((phase_ > 0) | (lane_ == goal)))  # a change begins from a settled lane, not the goal's
        changing = (phase_ > 0) | begin
        v1 = np.clip(v_ + a * dt, 0.0, search.top_speed)
        s1 = s_ + (v_ + v1) / 2 * dt
        ok &= _safe(search, lane_, lane_ + toward * changing, s_, s1, v_, v1, others, t0, t0 + dt)
        phase1 = np.where(changing, phase_ + 1, 0)
        done = phase1 == search.change_steps
        lane1 = np.where(done, lane_ + toward, lane_)
        phase1 = np.where(done, 0, phase1)
        entering = (lane1 == goal) | ((phase1 > 0) & (lane1 + toward == goal))
        ok &= ~entering | (s1 >= window[0] - search.length)  # the goal lane begins at window[0]
        ok &= s1 <= window[1]  # past the window the goal is missed
        left = np.abs(goal - lane1) * search.change_steps - phase1 * (lane1 != goal)
        ok &= t0 + dt + left * dt <= search.horizon + 1e-9
        if k == 0:
            first_ = np.arange(m * n_a * 2) % (n_a * 2)
        cost1 = cost_ + (np.maximum(-a, 0.0) + search.lag * left) * dt
        if t0 + dt <= search.lookahead + 1e-9:
            ahead_ = lane1 + toward * phase1 / search.change_steps
        lane, phase, s, v, cost, first, ahead = (x[ok] for x in (lane1, phase1, s1, v1, cost1, first_, ahead_))
        if not len(s):
            return None
        arrived = np.flatnonzero((lane == goal) & (phase == 0) & (s >= window[0]))
        if len(arrived):
            i = arrived[np.argmin(cost[arrived])]
            return GapPlan(float(accels[first[i] // 2]), bool(first[i] % 2) or phase0 > 0, t0 + dt, float(ahead[i]))
        lane, phase, s, v, cost, first, ahead = _merge(search, lane, phase, s, v, cost, first, ahead)
    return None


def _safe(search: GapSearch, lane_from: np.ndarray, lane_to: np.ndarray, s_before: np.ndarray, s_after: np.ndarray,
          v_before: np.ndarray, v_after: np.ndarray, others: np.ndarray, t_before: float,
          t_after: float) -> np.ndarray:
    """``(M,)``: whether the EV, holding ``lane_from`` and ``lane_to`` over a step, keeps the safe gap to every other
    vehicle in those lanes at the step's start and end and passes none of them within it (module doc)."""
    if not len(others):
        return np.ones(len(s_before), bool)
    o_lane, o_s, o_v = others[:, 0], others[:, 1], others[:, 2]
    held = (o_lane[None] == lane_from[:, None]) | (o_lane[None] == lane_to[:, None])  # (M, N)
    ahead_after = (o_s + o_v * t_after)[None] - s_after[:, None]
    ahead_before = (o_s + o_v * t_before)[None] - s_before[:, None]
    passed = np.sign(ahead_after) != np.sign(ahead_before)
    unsafe = passed | _short(search, ahead_after, v_after, o_v) | _short(search, ahead_before, v_before, o_v)
    return ~(held & unsafe).any(axis=1)


def _short(search: GapSearch, ahead: np.ndarray, v: np.ndarray, o_v: np.ndarray) -> np.ndarray:
    """``(M, N)``: whether the EV at speed ``v (M,)`` is nearer than the safe gap (module doc) to each other vehicle
    ``ahead (M, N)`` m ahead of it (behind: < 0) at speed ``o_v (N,)``."""
    v, o_v = v[:, None], o_v[None]
    front = search.gap + np.maximum(v ** 2 - o_v ** 2, 0.0) / (2 * search.brake)
    rear = search.gap + np.maximum(o_v ** 2 - v ** 2, 0.0) / (2 * search.brake)
    return np.abs(ahead) - search.length < np.where(ahead >= 0, front, rear)


def _merge(search: GapSearch, lane, phase, s, v, cost, first, ahead):
    """The states merged on (lane, phase, speed to 2 m/s, position to 2 m), the least braking kept; then at most
    ``per_group`` of each (lane, phase, speed to 4 m/s), those furthest ahead."""
    key = np.stack([lane, phase, np.round(v / 2).astype(int), np.round(s / 2).astype(int)])
    order = np.lexsort((cost, *key[::-1]))  # by key, cheapest first within a key
    fresh = np.ones(len(order), bool)
    fresh[1:] = (key[:, order[1:]] != key[:, order[:-1]]).any(axis=0)
    keep = order[fresh]
    group = (lane[keep] * search.change_steps + phase[keep]) * 100 + np.floor(v[keep] / 4).astype(int)
    order = np.lexsort((-s[keep], group))
    g = group[order]
    starts = np.r_[0, np.flatnonzero(g[1:] != g[:-1]) + 1]
    rank = np.arange(len(g)) - np.repeat(starts, np.diff(np.r_[starts, len(g)]))
    keep = keep[order[rank < search.per_group]]
    return lane[keep], phase[keep], s[keep], v[keep], cost[keep], first[keep], ahead[keep]
