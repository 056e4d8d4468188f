"""Safety metrics of one episode, computed from its per-step trace, and their summary over episodes.

A trace is a dict of equal-length per-step lists, as :func:`bimp.agents.rollout.rollout` records them from
the env's ``info`` (evaluation never re-derives what the env already measured):
``collision``, ``offroad`` (bool); ``ov_distance`` (K floats, m); ``edge_distance`` (m); ``ttc`` (s, inf if no
closing OV); ``lateral_error`` (m); ``speed_error`` (m/s); ``input`` ([a, delta]); ``constraints`` (dicts of
values <= 0 when satisfied, see :mod:`bimp.envs.scenarios`); ``plan_ms`` (ms spent in ``act``); ``s`` (arc length
along the road, m; gives ``progress_m``, e.g. higher when the EV overtakes instead of following); ``x``, ``y``,
``heading``, ``speed`` (the EV's state, m, rad, m/s); ``contact`` (None, or the OV in contact: see
:func:`bimp.envs.scene.attribution_info`) and ``speed_limit`` (m/s), which the closed-loop score reads
(:func:`closed_loop_score`, ``docs/suite.md``).
"""

from __future__ import annotations

import math
from types import MappingProxyType

import numpy as np
from numpy.typing import ArrayLike
from scipy.signal import savgol_filter

from bimp.agents.evaluation.stats import mean_summary, rate_summary
from bimp.envs.scene import VEHICLE_WIDTH

SCORE_METRICS = ("at_fault_collision_rate", "score", "score_progress", "score_ttc", "score_speed", "score_comfort")
METRICS = (
    "success_rate", "collision_rate", "offroad_rate", "input_violation_rate", "rate_violation_rate",
    "min_distance_m", "min_ttc_s", "rms_lateral_error_m", "rms_speed_error_mps", "max_abs_jerk",
    "plan_time_ms_p50", "plan_time_ms_p95", "progress_m", "overtake_rate", *SCORE_METRICS,
)
# One 0/1 outcome per episode: summarized as a proportion with a Wilson interval.
BINARY = ("success_rate", "collision_rate", "offroad_rate", "overtake_rate", "at_fault_collision_rate")
# Constraint values this small count as satisfied: float32 round-off of an action sitting on its bound.
TOLERANCE = 1e-6


def episode_metrics(trace: dict, dt: float, truncated: bool) -> dict[str, float | None]:
    """Scalar metrics of one episode. ``truncated``: the episode reached its time limit (not terminated).

    Rates over steps (``input_violation_rate``, ``rate_violation_rate``) are the share of steps whose
    commanded input breaks a bound; ``success_rate`` of one episode is 1 when it reached the env's goal where the
    env has one (``info["goal"]`` a bool: a wrapped highway-env env's exit taken, intersection crossed, roundabout
    left, merge road's end; the time limit alone is not enough there), else the time limit (``goal`` None or
    absent), without collision or leaving the road. ``min_ttc_s`` is ``None`` when no OV was ever closing in.
    """
    c = trace["constraints"]
    inputs = np.array(trace["input"], dtype=float).reshape(-1, 2)
    input_viol = [max(k["accel_min"], k["accel_max"], k["steer"]) > TOLERANCE for k in c]
    rate_viol = [max(k["accel_rate"], k["steer_rate"]) > TOLERANCE for k in c]
    collision, offroad = any(trace["collision"]), any(trace["offroad"])
    goals = _goals(trace)
    reached = any(goals) if goals else truncated
    ttc = float(np.min(trace["ttc"])) if trace["ttc"] else math.inf
    jerk = np.abs(np.diff(inputs[:, 0])) / dt if len(inputs) > 1 else np.zeros(1)
    plan = np.array(trace["plan_ms"], dtype=float)
    return {
        "success_rate": float(reached and not collision and not offroad),
        "collision_rate": float(collision),
        "offroad_rate": float(offroad),
        "input_violation_rate": float(np.mean(input_viol)),
        "rate_violation_rate": float(np.mean(rate_viol)),
        "min_distance_m": float(np.min(trace["ov_distance"])),
        "min_ttc_s": ttc if math.isfinite(ttc) else None,
        "rms_lateral_error_m": float(np.sqrt(np.mean(np.square(trace["lateral_error"])))),
        "rms_speed_error_mps": float(np.sqrt(np.mean(np.square(trace["speed_error"])))),
        "max_abs_jerk": float(jerk.max()),
        "plan_time_ms_p50": float(np.percentile(plan, 50)),
        "plan_time_ms_p95": float(np.percentile(plan, 95)),
        "progress_m": float(trace["s"][-1] - trace["s"][0]) if "s" in trace else None,
        # the EV ends ahead of OV1, the vehicle it started behind in its lane (overtaking only: else None)
        "overtake_rate": (float(trace["ahead_of_ov1"][-1]) if trace.get("ahead_of_ov1")
                          and trace["ahead_of_ov1"][-1] is not None else None),
        **closed_loop_score(trace, dt, truncated),
    }


# --- the closed-loop score (docs/suite.md) ------------------------------------------------------------------------
# nuPlan's thresholds and weights, cited where they are nuPlan's; docs/suite.md says where this score differs.
STOPPED_SPEED = 0.05  # m/s: a vehicle this slow is stopped (nuPlan's stopped_speed_threshold, 5e-2)
REAR_CONE = np.deg2rad(30.0)  # rad: "behind" is within 30 deg of straight behind (nuPlan's is_agent_behind: > 150 deg)
# m/s: the EV moves across its road this fast or faster toward the OV: it is changing lanes. Above the sway of a
# planner keeping its lane (EnKTS on development seed 3 of the keep-lane overtaking and the emergency brake: at most
# 0.37 m/s, 95% of steps under 0.23), below a lane change's (4 m crossed in 2-3 s: 1.3-2 m/s on average).
LANE_CHANGE_SPEED = 0.5
TTC_BOUND = 0.95  # s: least time to collision (nuPlan's least_min_ttc)
OVERSPEED_BOUND = 2.23  # m/s: overspeed at which the speed term reaches 0 when held throughout (nuPlan's 5 mph)
MAX_LON_JERK = 4.13  # m/s^3: nuPlan's max_abs_lon_jerk
MAX_LAT_ACCEL = 4.89  # m/s^2: nuPlan's max_abs_lat_accel
# Savitzky-Golay windows [steps, odd so each fit is centred on its step], polynomial order 2, as nuPlan's comfort
# filters: acceleration smoothed over 9 steps (nuPlan: 8), jerk as the derivative of that over 15 (nuPlan's),
# yaw rate as the derivative of the heading over 5 (nuPlan's approximate_derivatives default).
ACCEL_WINDOW, JERK_WINDOW, YAW_RATE_WINDOW = 9, 15, 5
# nuPlan's weighted average; read-only: every record's score depends on them
WEIGHTS = MappingProxyType({"progress": 5.0, "ttc": 5.0, "speed": 4.0, "comfort": 2.0})


def contact_at_fault(contact: dict) -> bool:
    """Whether the EV is at fault for a contact (``info["contact"]``, :func:`bimp.envs.scene.attribution_info`):
    nuPlan's collision types, read in the EV's body frame, the first that matches deciding:

    1. the EV stopped (``ev_speed`` < :data:`STOPPED_SPEED`): not at fault;
    2. the OV stopped (``ov_speed`` < :data:`STOPPED_SPEED`): at fault (the EV drove into it);
    3. hit from behind: the OV's centre behind the EV's (``rel_x < 0``) within :data:`REAR_CONE` of its axis and the
       OV closing (its speed along the EV's heading above the EV's): not at fault;
    4. hit in front: the OV's centre ahead (``rel_x > 0``) and less than a vehicle width to the side (the
       footprints overlap side-on: the EV's front met it): at fault;
    5. otherwise a lateral contact: at fault when the EV moves across its road toward the OV's side at
       :data:`LANE_CHANGE_SPEED` or more (it was changing lanes into it), else not (the OV came across).
    """
    rel_x, rel_y = contact["rel_x"], contact["rel_y"]
    ev_speed, ov_speed = contact["ev_speed"], contact["ov_speed"]
    if ev_speed < STOPPED_SPEED:
        return False
    if ov_speed < STOPPED_SPEED:
        return True
    closing = ov_speed * math.cos(contact["rel_heading"]) > ev_speed
    if rel_x < 0.0 and abs(rel_y) <= math.tan(REAR_CONE) * -rel_x and closing:
        return False
    if rel_x > 0.0 and abs(rel_y) < VEHICLE_WIDTH:
        return True
    return math.copysign(1.0, rel_y) * contact["ev_lateral_speed"] >= LANE_CHANGE_SPEED


def at_fault_collision(trace: dict) -> float | None:
    """1.0 when some contact of the episode is the EV's fault (:func:`contact_at_fault`), 0.0 when none is (or none
    happened); None for a trace without ``contact`` (recorded before it existed) or with a collision the env
    described no contact for (an env that does not report it)."""
    contacts = trace.get("contact")
    if contacts is None or len(contacts) != len(trace["collision"]):
        return None
    if any(hit and contact is None for hit, contact in zip(trace["collision"], contacts)):
        return None
    return float(any(contact_at_fault(c) for c in contacts if c is not None))


def _savgol(y: np.ndarray, window: int, dt: float, deriv: int) -> np.ndarray:
    """Savitzky-Golay filter of order 2 over ``window`` steps (fewer on a shorter series, kept odd; zeros, i.e. no
    change measured, on a series of fewer than 3 steps), ``deriv`` its derivative order, ``dt`` [s]."""
    n = len(y)
    window = min(window, n if n % 2 else n - 1)
    if window < 3:
        return np.zeros(n)
    return savgol_filter(y, window_length=window, polyorder=2, deriv=deriv, delta=dt, mode="interp")


def comfort_signals(speed: ArrayLike, heading: ArrayLike, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """``(longitudinal jerk [m/s^3], lateral acceleration [m/s^2])`` along an episode from the EV's ``speed (n,)``
    [m/s] and ``heading (n,)`` [rad] at each step, ``dt`` [s] apart; ``(n - 1,)`` and ``(n,)``.

    Longitudinal acceleration: the speed's step differences (the EV's speed changes by acceleration x dt per step,
    so this is its acceleration, also where the speed is held at 0: a commanded brake at a standstill is none),
    smoothed over :data:`ACCEL_WINDOW` steps; jerk: its derivative over :data:`JERK_WINDOW`. Lateral acceleration:
    speed x yaw rate, the yaw rate the derivative of the unwrapped heading over :data:`YAW_RATE_WINDOW`, smoothed over
    :data:`ACCEL_WINDOW` (the centripetal acceleration of the driven path; the bicycle's slip angle left out)."""
    v = np.asarray(speed, float)
    accel = _savgol(np.diff(v) / dt, ACCEL_WINDOW, dt, 0) if len(v) > 1 else np.zeros(0)
    jerk = _savgol(accel, JERK_WINDOW, dt, 1) if len(accel) else accel
    yaw_rate = _savgol(np.unwrap(np.asarray(heading, float)), YAW_RATE_WINDOW, dt, 1)
    return jerk, _savgol(v * yaw_rate, ACCEL_WINDOW, dt, 0)


def closed_loop_score(trace: dict, dt: float, truncated: bool) -> dict[str, float | None]:
    """The closed-loop score of one episode in nuPlan's style (``docs/suite.md``), from its trace (``dt`` [s] per
    step) and whether it ran to its time limit (``truncated``): ``at_fault_collision_rate``
    (:func:`at_fault_collision`), ``score`` and its parts, each in [0, 1]::

        score          = (no at-fault collision) x (never off-road) x (goal not missed)
                         x (5 progress + 5 ttc + 4 speed + 2 comfort) / 16
        goal missed    = the env has a goal (``goal`` a bool at some step) and the episode ran to its time limit
                         without a collision and without reaching it
        score_progress = min(1, max(0, progress_m) / reachable_m),  reachable_m = dt x sum of speed_limit over the
                         steps progress_m covers (the second to the last): driving at the limit throughout
                         (1 where nothing was reachable)
        score_ttc      = 1 if ttc >= 0.95 s at every step where it is finite (an OV ahead closing), else 0
        score_speed    = max(0, 1 - mean over steps of max(0, speed - speed_limit) / 2.23 m/s)
        score_comfort  = 1 if |longitudinal jerk| <= 4.13 m/s^3 and |lateral acceleration| <= 4.89 m/s^2 at every
                         step (:func:`comfort_signals`), else 0

    Every value None for a trace without what it reads (``contact``, ``speed_limit``, ``speed``, ``heading``, ``s``:
    recorded before the score existed, or by an env that does not report them); ``at_fault_collision_rate`` needs
    only ``contact``. A ``ttc`` of None (a stored trace: JSON has no inf) is no closing OV.
    """
    at_fault = at_fault_collision(trace)
    limits = trace.get("speed_limit")
    needed = ("speed", "heading", "s", "ttc", "offroad")
    if at_fault is None or not limits or any(v is None for v in limits) or any(not trace.get(k) for k in needed):
        return {"at_fault_collision_rate": at_fault, **{name: None for name in SCORE_METRICS[1:]}}
    limit = np.asarray(limits, float)
    speed = np.asarray(trace["speed"], float)
    progress = float(trace["s"][-1] - trace["s"][0])
    reachable = dt * float(np.sum(limit[1:]))
    ttc = np.array([math.inf if t is None else t for t in trace["ttc"]], float)
    jerk, lateral = comfort_signals(speed, trace["heading"], dt)
    parts = {
        "progress": min(1.0, max(0.0, progress) / reachable) if reachable > 0.0 else 1.0,
        "ttc": float(bool(np.all(ttc[np.isfinite(ttc)] >= TTC_BOUND))),
        "speed": max(0.0, 1.0 - float(np.mean(np.maximum(speed - limit, 0.0))) / OVERSPEED_BOUND),
        "comfort": float(bool(np.all(np.abs(jerk) <= MAX_LON_JERK) and np.all(np.abs(lateral) <= MAX_LAT_ACCEL))),
    }
    # Waiting behind two-way-overtake's slow vehicle is no way to complete the route; an episode a collision ended
    # is judged by the collision gate alone (not at fault: the goal was still to come).
    goals = _goals(trace)
    missed = truncated and bool(goals) and not any(goals) and not any(trace["collision"])
    gate = (1.0 - at_fault) * (0.0 if any(trace["offroad"]) else 1.0) * (0.0 if missed else 1.0)
    weighted = sum(WEIGHTS[k] * parts[k] for k in WEIGHTS) / sum(WEIGHTS.values())
    return {"at_fault_collision_rate": at_fault, "score": gate * weighted,
            **{f"score_{k}": float(v) for k, v in parts.items()}}


def _goals(trace: dict) -> list[bool]:
    """The goal flags of an env with a goal (two-way-overtake's pass, exit-v0's exit ...: a bool every step); empty
    for an env without one (None every step, or no ``goal`` in the trace)."""
    return [g for g in trace.get("goal") or () if g is not None]


def record_label(record: dict) -> str:
    """A record's label (records older than labels use the policy name). Here, below
    :mod:`bimp.agents.evaluation.records`, because :func:`summarize` groups by it."""
    return record.get("label", record["policy"])


def code_version(record: dict) -> str:
    """The code that made a record: its ``git_commit`` (``+dirty`` when the tree had uncommitted changes), as the
    summaries' ``code_versions`` name it; ``bimp VERSION`` for a record made outside a git checkout (no commit), where
    the package version is all there is. Two dirty records of one commit cannot be told apart: the same version."""
    commit = record.get("git_commit")
    if commit:
        return f"{commit}{'+dirty' if record.get('git_dirty') else ''}"
    return f"bimp {record.get('bimp_version') or '?'} (no git commit)"


def record_missed_goal(record: dict) -> bool:
    """The goal gate of :func:`closed_loop_score` read from an episode record, from what every record holds: an
    episode that ran to its time limit (``truncated``) without a collision, on the road, and failed is one whose env
    has a goal it did not reach (without a goal such an episode succeeds). An off-road episode is not counted here,
    where the trace's gate may count it: its score is 0 by the off-road gate either way.
    :mod:`bimp.agents.evaluation.migrate` gates the scores recorded before the goal gate with it."""
    m = record.get("metrics") or {}
    return bool(record.get("truncated")) and m.get("collision_rate") == 0.0 and m.get("offroad_rate") == 0.0 \
        and m.get("success_rate") == 0.0


def summarize(records: list[dict]) -> dict[str, dict]:
    """Summary per ``label/scenario`` of episode records (one per label, scenario and seed: see
    :func:`bimp.agents.evaluation.evaluate.latest_records`).

    ``fallback_seeds`` and ``fallback_steps``: the episodes where the planner fell back on at least one step, and
    the fallback steps out of ``steps`` (all steps of the results).

    Results are the episodes that ran to their end (``status`` "ok"); an episode that raised is not a result:
    it is counted in ``errors`` with its seed in ``error_seeds`` and left out of every metric. Episode
    outcomes (``BINARY``) get ``{mean, ci_low, ci_high, k, n}`` with the Wilson 95% interval, the other
    metrics ``{mean, ci_low, ci_high, std, min, max, n}`` with a bootstrap 95% interval of the mean.
    ``failed_seeds`` lists, per outcome, the seeds where it went wrong (no success, a collision, off-road).
    """
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in records:
        groups.setdefault((record_label(r), r["scenario"]), []).append(r)
    out = {}
    for (label, scenario), rs in sorted(groups.items()):
        rs = sorted(rs, key=lambda r: r["seed"])
        ok = [r for r in rs if r["status"] == "ok"]
        entry: dict = {
            "policy": label, "policy_name": rs[0]["policy"], "scenario": scenario,
            "config_hash": sorted({str(r.get("config_hash")) for r in rs}),
            # resume matches on the config, not the code: say when a row mixes records of several code versions
            "code_versions": sorted({f"{r.get('git_commit')}{'+dirty' if r.get('git_dirty') else ''}" for r in rs}),
            "episodes": len(ok), "errors": len(rs) - len(ok),
            "error_seeds": [r["seed"] for r in rs if r["status"] != "ok"],
            "failed_seeds": {
                "success": [r["seed"] for r in ok if not r["metrics"]["success_rate"]],
                "collision": [r["seed"] for r in ok if r["metrics"]["collision_rate"]],
                "offroad": [r["seed"] for r in ok if r["metrics"]["offroad_rate"]],
            },
            # A planner that found no usable plan held or braked instead (its step_info "fallback"): driving on
            # fallbacks is a failure of the planner even where no collision followed, so the summary says so.
            "fallback_seeds": [r["seed"] for r in ok if _fallback_steps(r)],
            "fallback_steps": sum(_fallback_steps(r) for r in ok),
            "steps": sum(r.get("steps") or 0 for r in ok),
        }
        for name in METRICS:
            values = [r["metrics"][name] for r in ok if r["metrics"].get(name) is not None]
            entry[name] = rate_summary(values) if name in BINARY else mean_summary(values)
        out[f"{label}/{scenario}"] = entry
    return out


def _fallback_steps(record: dict) -> int:
    """How many steps of an episode the planner fell back (``policy_info.fallback_steps``, from the planner's
    per-step ``step_info``: :func:`bimp.agents.evaluation.evaluate.step_info_summary`); 0 for a policy that reports
    none."""
    steps = (record.get("policy_info") or {}).get("fallback_steps")
    return len(steps) if isinstance(steps, list) else 0
