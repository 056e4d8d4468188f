"""Safety metrics of one episode, computed from its per-step trace, and their summary over episodes.

A trace is a dict of equal-length per-step lists, as :func:`bimp.agents.rollout.rollout` records them from
the env's ``info`` (evaluation never re-derives what the env already measured):
``collision``, ``offroad`` (bool); ``ov_distance`` (K floats, m); ``edge_distance`` (m); ``ttc`` (s, inf if no
closing OV); ``lateral_error`` (m); ``speed_error`` (m/s); ``input`` ([a, delta]); ``constraints`` (dicts of
values <= 0 when satisfied, see :mod:`bimp.envs.scenarios`); ``plan_ms`` (ms spent in ``act``); ``s`` (arc length
along the road, m; gives ``progress_m``, e.g. higher when the EV overtakes instead of following).
"""

from __future__ import annotations

import math

import numpy as np

from bimp.agents.stats import mean_summary, rate_summary

METRICS = (
    "success_rate", "collision_rate", "offroad_rate", "input_violation_rate", "rate_violation_rate",
    "min_distance_m", "min_ttc_s", "rms_lateral_error_m", "rms_speed_error_mps", "max_abs_jerk",
    "plan_time_ms_p50", "plan_time_ms_p95", "progress_m", "overtake_rate",
)
# One 0/1 outcome per episode: summarized as a proportion with a Wilson interval.
BINARY = ("success_rate", "collision_rate", "offroad_rate", "overtake_rate")
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
    goals = [g for g in trace.get("goal") or () if g is not None]  # an env with a goal reports a bool every step
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
    }


def summarize(records: list[dict]) -> dict[str, dict]:
    """Summary per ``label/scenario`` of episode records (one per label, scenario and seed: see
    :func:`bimp.agents.evaluate.latest_records`).

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
        groups.setdefault((r.get("label", r["policy"]), r["scenario"]), []).append(r)
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
    per-step ``step_info``: :func:`bimp.agents.evaluate.step_info_summary`); 0 for a policy that reports none."""
    steps = (record.get("policy_info") or {}).get("fallback_steps")
    return len(steps) if isinstance(steps, list) else 0
