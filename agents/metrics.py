"""Safety metrics of one episode, computed from its per-step trace, and their summary over episodes.

A trace is a dict of equal-length per-step lists, as :func:`agents.evaluate.run_episode` records them from
the env's ``info`` (evaluation never re-derives what the env already measured):
``collision``, ``offroad`` (bool); ``ov_distance`` (K floats, m); ``edge_distance`` (m); ``ttc`` (s, inf if no
closing OV); ``lateral_error`` (m); ``speed_error`` (m/s); ``input`` ([a, delta]); ``constraints`` (dicts of
values <= 0 when satisfied, see :mod:`envs.scenarios`); ``plan_ms`` (ms spent in ``act``); ``s`` (arc length
along the road, m; gives ``progress_m``, e.g. higher when the EV overtakes instead of following).
"""

from __future__ import annotations

import math

import numpy as np

METRICS = (
    "success_rate", "collision_rate", "offroad_rate", "input_violation_rate", "rate_violation_rate",
    "min_distance_m", "min_ttc_s", "rms_lateral_error_m", "rms_speed_error_mps", "max_abs_jerk",
    "plan_time_ms_p50", "plan_time_ms_p95", "progress_m",
)
# Constraint values this small count as satisfied: float32 round-off of an action sitting on its bound.
TOLERANCE = 1e-6


def episode_metrics(trace: dict, dt: float, truncated: bool) -> dict[str, float | None]:
    """Scalar metrics of one episode. ``truncated``: the episode reached its time limit (not terminated).

    Rates over steps (``input_violation_rate``, ``rate_violation_rate``) are the share of steps whose
    commanded input breaks a bound; ``success_rate`` of one episode is 1 when it reached the time limit
    without collision or leaving the road. ``min_ttc_s`` is ``None`` when no OV was ever closing in.
    """
    c = trace["constraints"]
    inputs = np.array(trace["input"], dtype=float).reshape(-1, 2)
    input_viol = [max(k["accel_min"], k["accel_max"], k["steer"]) > TOLERANCE for k in c]
    rate_viol = [max(k["accel_rate"], k["steer_rate"]) > TOLERANCE for k in c]
    collision, offroad = any(trace["collision"]), any(trace["offroad"])
    ttc = float(np.min(trace["ttc"])) if trace["ttc"] else math.inf
    jerk = np.abs(np.diff(inputs[:, 0])) / dt if len(inputs) > 1 else np.zeros(1)
    plan = np.array(trace["plan_ms"], dtype=float)
    return {
        "success_rate": float(truncated and not collision and not offroad),
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
    }


def summarize(records: list[dict]) -> dict[str, dict]:
    """Summary of episode records (``{"scenario", "policy", "status", "metrics"}``) per ``policy/scenario``.

    Each metric gets ``mean``, ``std`` (over episodes), ``min``, ``max``; an episode that raised counts as
    an unsuccessful episode and is otherwise left out of the metrics (``errors`` counts them).
    """
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in records:
        groups.setdefault((r["policy"], r["scenario"]), []).append(r)
    out = {}
    for (policy, scenario), rs in sorted(groups.items()):
        ok = [r["metrics"] for r in rs if r["status"] == "ok"]
        entry: dict = {"policy": policy, "scenario": scenario, "episodes": len(rs), "errors": len(rs) - len(ok)}
        for name in METRICS:
            values = [m[name] for m in ok if m[name] is not None]
            if name == "success_rate":
                values += [0.0] * entry["errors"]
            entry[name] = ({"mean": float(np.mean(values)), "std": float(np.std(values)),
                            "min": float(np.min(values)), "max": float(np.max(values))}
                           if values else {"mean": None, "std": None, "min": None, "max": None})
        out[f"{policy}/{scenario}"] = entry
    return out
