"""The checks every bimp env shares: its action (:func:`checked_action`), its policy frequency
(:func:`check_policy_frequency`) and highway-env's own config keys (:func:`check_highway_config`).

The paper's envs (:mod:`bimp.envs.scenarios`) and the highway-env adapter (:mod:`bimp.envs.highway.adapter`, the
suite's families included) call these same functions, so an action or a key is refused the same way on every env.
Every refusal is a one-line ``ValueError`` naming the key (or the action) and the value, and saying what it must be.

highway-env reads its config keys without checking them: a string where it counts vehicles, a fraction where it
counts lanes, a lane index past the road raise its raw ``TypeError``/``IndexError`` deep in a reset; a NaN reward
weight makes every reward NaN; and ``Road.step`` checks every pair of vehicles at every simulation step, so ten
thousand vehicles hang the first step. :data:`KEY_RULES` says, from highway-env 1.12's source
(``highway_env/envs/*.py``), what each key it reads must be; vehicle counts are capped at :data:`MAX_VEHICLES`.
"""

from __future__ import annotations

import numbers
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from highway_env import utils
from highway_env.envs.exit_env import ExitEnv
from highway_env.envs.highway_env import HighwayEnv
from highway_env.envs.intersection_env import IntersectionEnv
from highway_env.envs.merge_env import MergeEnv
from highway_env.envs.racetrack_env import RacetrackEnv
from highway_env.envs.roundabout_env import RoundaboutEnv
from highway_env.envs.u_turn_env import UTurnEnv
from highway_env.vehicle.behavior import IDMVehicle

from bimp.envs.scene import POLICY_FREQUENCY

# highway-env checks every pair of vehicles at every simulation step. On highway-v0 (2 shared cores) its default 50
# take 0.03 s a step, 200 take 0.2 s, 400 already 1 s (a 40 s episode: 7 minutes); 10000 hang the first step > 40 s.
MAX_VEHICLES = 200
MAX_LANES = 20  # every vehicle looks for its closest lane among all of them at every step
MAX_SCREEN = 10_000  # pixels a side: pygame allocates the whole frame, 4 bytes a pixel


def is_real(value: Any) -> bool:
    """A real number that is not a bool (``True`` would pass for 1 anywhere numpy or Python computes with it)."""
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def is_int(value: Any) -> bool:
    """An integer (Python's or numpy's) that is not a bool."""
    return isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_))


def checked_flag(name: str, value: Any) -> bool:
    """``value`` when it is a bool; else a one-line ``ValueError`` naming ``name`` (``"no"`` or 0 would pass for
    false in an ``if``)."""
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be true or false, got {_shown(value)}")
    return bool(value)


def _shown(value: Any, limit: int = 80) -> str:
    # One line, whatever the value: an array's repr spans lines.
    text = " ".join(repr(value).split())
    return text if len(text) <= limit else text[:limit - 3] + "..."


def _has_bool(value: Any) -> bool:
    # numpy turns a bool among numbers into 1 or 0 (np.asarray([1.0, True]) is a float array): look before it does.
    if isinstance(value, (list, tuple)):
        return any(_has_bool(v) for v in value)
    return isinstance(value, (bool, np.bool_))


def checked_action(action: Any, size: int = 2) -> np.ndarray:
    """``action`` as a float array of shape ``(size,)``: real numbers only (a float or int array, a list of floats or
    ints); a numeric string, a complex number, a bool, an array of bool/complex/str/object dtype, a wrong shape or a
    non-finite value raises ``ValueError`` naming what was given. Not clipped: the envs clip to [-1, 1]."""
    try:
        raw = np.asarray(action)
    except ValueError:  # a ragged sequence
        raw = np.asarray(None)
    if raw.dtype.kind not in "iuf" or _has_bool(action):
        kind = f"an array of dtype {raw.dtype}" if isinstance(action, np.ndarray) else f"a {type(action).__name__}"
        raise ValueError(f"action must be {size} real numbers (a float array, or a list of floats or ints), got "
                         f"{kind} {_shown(action)}")
    out = raw.astype(float).reshape(-1)
    if out.shape != (size,):
        raise ValueError(f"action must have shape ({size},), got {np.shape(action)}")
    if not np.all(np.isfinite(out)):
        raise ValueError(f"action must be finite, got {out}")
    return out


def check_policy_frequency(value: Any, where: str) -> None:
    """``ValueError`` unless ``value`` is bimp's policy frequency (10 Hz): the planners plan with a 0.1 s model, so an
    env stepping at another rate would run them on dynamics they do not predict."""
    if not (is_real(value) and value == POLICY_FREQUENCY):
        raise ValueError(f"{where}: config policy_frequency={value!r} cannot be honoured: bimp's planners plan at "
                         f"dt = 0.1 s (policy_frequency {POLICY_FREQUENCY})")


# --- highway-env's keys ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Rule:
    """What one highway-env key must be: ``what`` (as the message says it), ``admits`` (the test), ``why``."""

    what: str
    admits: Callable[[Any], bool]
    why: str = ""


def _int(low: int, high: int | None = None, why: str = "") -> Rule:
    what = f"an int >= {low}" if high is None else f"an int in [{low}, {high}]"
    return Rule(what, lambda v: is_int(v) and v >= low and (high is None or v <= high), why)


def _real(low: float = -np.inf, high: float = np.inf, open_low: bool = False, why: str = "") -> Rule:
    if np.isfinite(low) and np.isfinite(high):
        what = f"a real number in {'(' if open_low else '['}{low:g}, {high:g}]"
    else:
        bound = f" {'>' if open_low else '>='} {low:g}" if np.isfinite(low) else ""
        what = "a finite real number" + bound
    return Rule(what, lambda v: is_real(v) and abs(v) < 1e300 and bool(np.isfinite(v))  # 10**400: no float
                and (v > low if open_low else v >= low) and v <= high, why)


def _pair(ordered: bool, why: str = "") -> Rule:
    what = "a pair [lo, hi] of finite real numbers with lo < hi" if ordered else "a pair [x, y] of finite real numbers"

    def admits(v: Any) -> bool:
        ok = (isinstance(v, (list, tuple, np.ndarray)) and np.ndim(v) == 1 and len(v) == 2
              and all(is_real(x) and np.isfinite(x) for x in v))
        return bool(ok and (not ordered or v[0] < v[1]))
    return Rule(what, admits, why)


def _or_none(rule: Rule) -> Rule:
    return Rule(f"None or {rule.what}", lambda v: v is None or rule.admits(v), rule.why)


def _traffic_class(path: Any) -> bool:
    if not isinstance(path, str):
        return False
    try:
        cls = utils.class_from_path(path)  # what highway-env does with it at every reset
    except (ImportError, AttributeError, ValueError):
        return False
    return isinstance(cls, type) and issubclass(cls, IDMVehicle)


_BOOL = Rule("true or false (a bool)", lambda v: isinstance(v, (bool, np.bool_)))
_COUNT = _int(0, MAX_VEHICLES, f"at most {MAX_VEHICLES} vehicles: highway-env checks every pair of vehicles at every "
                              "simulation step, so more would take minutes")
_WEIGHT = _real(why="a reward weight: highway-env sums the weighted rewards")

KEY_RULES: Mapping[str, Rule] = {
    "lanes_count": _int(1, MAX_LANES, f"at most {MAX_LANES} lanes: every vehicle looks for its lane among all"),
    "vehicles_count": _COUNT,
    "initial_vehicle_count": _COUNT,
    "other_vehicles": _COUNT,
    "controlled_vehicles": Rule("1", lambda v: is_int(v) and v == 1, "bimp drives one EV: the adapter's action, "
                                "observation and safety info are that one vehicle's"),
    # Its upper end, lanes_count - 1, is checked across the keys (check_highway_config).
    "initial_lane_id": _or_none(_int(0, why="the EV's lane, an index of the road's lanes_count lanes")),
    "duration": _real(0.0, open_low=True, why="the episode's length, s"),
    # highway-env's default gap between two vehicles is some 20 m (12 m + 1 s at the speed, less with more lanes).
    "ego_spacing": _real(0.0, 10.0, open_low=True, why="the EV starts 3 x ego_spacing default gaps down the road: "
                                                       "more puts it past the end of exit-v0's"),
    "vehicles_density": _real(0.1, 10.0, why="highway-env spaces its traffic 1 / vehicles_density default gaps apart: "
                                             "below, kilometres apart, off the end of the road; at 1e-320, infinitely"),
    "spawn_probability": _real(0.0, 1.0, why="a probability"),
    "speed_limit": _real(0.0, open_low=True, why="the lanes' speed limit, m/s"),
    "lane_centering_cost": _real(0.0, why="highway-env divides by 1 + lane_centering_cost * lateral^2"),
    **{key: _WEIGHT for key in ("collision_reward", "right_lane_reward", "high_speed_reward", "lane_change_reward",
                                "merging_speed_reward", "goal_reward", "left_lane_reward", "arrived_reward",
                                "action_reward", "lane_centering_reward", "left_lane_constraint")},
    "reward_speed_range": _pair(True, "m/s: highway-env maps the speeds in it onto [0, 1]"),
    **{key: _BOOL for key in ("normalize_reward", "offroad_terminal", "terminate_off_road", "show_trajectories",
                              "render_agent", "manual_control", "real_time_rendering",
                              "neighbour_vehicles_connected_lanes")},
    "offscreen_rendering": _or_none(_BOOL),
    "screen_width": _int(1, MAX_SCREEN, "pixels"),
    "screen_height": _int(1, MAX_SCREEN, "pixels"),
    "scaling": _real(0.0, open_low=True, why="pixels per metre"),
    "centering_position": _pair(False, "the EV's place on the screen, as shares of its width and height"),
    "other_vehicles_type": Rule("the import path of a traffic vehicle class (IDMVehicle or a subclass, e.g. "
                                "'highway_env.vehicle.behavior.IDMVehicle')", _traffic_class),
    "incoming_vehicle_destination": _or_none(_int(0, 2, "an index of roundabout-v0's three exits")),
    "destination": Rule("None or one of 'o1', 'o2', 'o3'", lambda v: v is None or v in ("o1", "o2", "o3"),
                        "intersection-v0's exits (the EV enters at 'o0'); another name leaves the EV without a route"),
}
# exit-v0 draws its traffic's lanes with weights lane / sum(lanes): one lane sums to 0 and the weights are NaN.
_EXIT_LANES = _int(2, MAX_LANES, "exit-v0 puts its traffic on the lanes beside the EV's")

# The interval highway-env maps the summed reward from onto [0, 1] (utils.lmap divides by its width): the keys summed
# at its low and high ends (a number: a constant), and whether it maps only under normalize_reward. First match.
_NORMALIZED: tuple[tuple[type, tuple, tuple, bool], ...] = (
    (ExitEnv, ("collision_reward",), ("goal_reward",), True),
    (HighwayEnv, ("collision_reward",), ("high_speed_reward", "right_lane_reward"), True),
    (MergeEnv, ("collision_reward", "merging_speed_reward"), ("high_speed_reward", "right_lane_reward"), False),
    (RoundaboutEnv, ("collision_reward",), ("high_speed_reward",), True),
    (UTurnEnv, ("collision_reward",), ("high_speed_reward", "left_lane_reward"), True),
    (IntersectionEnv, ("collision_reward",), ("arrived_reward",), True),
    (RacetrackEnv, ("collision_reward",), (1.0,), False),
)


def _check_normalization(where: str, env_class: type, config: Mapping) -> None:
    for cls, low, high, optional in _NORMALIZED:
        if not issubclass(env_class, cls):
            continue
        if optional and not config.get("normalize_reward"):
            return
        ends = [sum(k if isinstance(k, float) else config[k] for k in keys) for keys in (low, high)]
        names = [" + ".join(k if isinstance(k, str) else f"{k:g}" for k in keys) for keys in (low, high)]
        mapped = f"highway-env maps the reward from [{names[0]}, {names[1]}] onto [0, 1]" + (
            " (normalize_reward)" if optional else "")
        for name, end in zip(names, ends):
            if not np.isfinite(end):  # weights each finite, their sum overflowed
                raise ValueError(f"{where}: config {name}={end:g} must sum to a finite number: {mapped}")
        if not ends[0] < ends[1]:
            top = f"{names[1]}={ends[1]:g}" if any(isinstance(k, str) for k in high) else names[1]
            raise ValueError(f"{where}: config {names[0]}={ends[0]:g} must be below {top}: {mapped}")
        return


def check_highway_config(where: str, env_class: type, config: Mapping, base: Mapping | None = None,
                         refuse_unknown: bool = True) -> None:
    """``ValueError`` (one line, naming ``where``, the key and the value) for a key of ``config`` that
    :data:`KEY_RULES` refuses, for a key outside ``env_class.default_config()`` where ``refuse_unknown`` (listing
    the valid keys), and for what must hold across keys: ``initial_lane_id`` below ``lanes_count``, and the
    reward's normalization interval not empty. ``base``: the config ``config`` updates (the class's defaults when
    None), for the keys it leaves out. Keys without a rule (``action``, the frequencies, a family's own) and those
    in ``env_class.CHECKED_KEYS`` (a suite family's ``duration``, ``lanes_count``) are left to their owners."""
    defaults = env_class.default_config()
    if refuse_unknown:
        unknown = sorted(set(config) - set(defaults), key=str)
        if unknown:
            raise ValueError(f"{where}: unknown config key(s) {unknown}; its keys are {sorted(defaults)}")
    for key, value in config.items():
        if key in getattr(env_class, "CHECKED_KEYS", ()):  # the class checks it itself, more strictly
            continue
        rule = _EXIT_LANES if key == "lanes_count" and issubclass(env_class, ExitEnv) else KEY_RULES.get(key)
        if rule is not None and not rule.admits(value):
            raise ValueError(f"{where}: config {key}={_shown(value)} must be {rule.what}"
                             + (f" ({rule.why})" if rule.why else ""))
    merged = {**defaults, **(base or {}), **config}
    lane, lanes = merged.get("initial_lane_id"), merged.get("lanes_count")
    if lane is not None and lanes is not None and lane >= lanes:
        raise ValueError(f"{where}: config initial_lane_id={lane!r} must be None or a lane index below "
                         f"lanes_count={lanes!r}")
    _check_normalization(where, env_class, merged)
