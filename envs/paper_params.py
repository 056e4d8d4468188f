"""The paper envs' scenario parameters: a drawn or fixed value per key (:class:`Param`), orders that must hold over
the ranges (:class:`Order`), and the checks of both and of the frequencies (``bimp.envs.scenarios``' docstring)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from bimp.envs.checks import check_policy_frequency, is_real


# --- scenario parameters ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Param:
    """One scenario parameter: its default (a number, or a ``(lo, hi)`` range drawn uniformly at each reset) and
    the interval ``[low, high]`` (ends excluded where ``*_open``) that every value must lie in; ``integer``
    parameters take integers and are drawn uniformly among the integers of the range."""

    default: float | tuple[float, float]
    doc: str
    low: float = -np.inf
    high: float = np.inf
    low_open: bool = False
    high_open: bool = False
    integer: bool = False

    @property
    def rule(self) -> str:
        lo_op, hi_op = (">" if self.low_open else ">="), ("<" if self.high_open else "<=")
        kind = "an integer " if self.integer else ""
        if np.isfinite(self.low) and np.isfinite(self.high):
            return f"{kind}in {'(' if self.low_open else '['}{_fmt(self.low)}, {_fmt(self.high)}" \
                   f"{')' if self.high_open else ']'}"
        if np.isfinite(self.low):
            return f"{kind}{lo_op} {_fmt(self.low)}"
        if np.isfinite(self.high):
            return f"{kind}{hi_op} {_fmt(self.high)}"
        return kind.strip() or "a finite number"

    def admits(self, v: float) -> bool:
        above = v > self.low if self.low_open else v >= self.low
        below = v < self.high if self.high_open else v <= self.high
        return bool(above and below and (not self.integer or float(v).is_integer()))


@dataclass(frozen=True)
class Order:
    """``later`` comes after ``earlier`` by at least ``by`` (more than ``by`` where ``strict``) for *every* pair of
    draws, i.e. ``min(later) - max(earlier)``; ``later_in_steps``: ``later`` counts policy steps and is compared in
    seconds (``x dt``)."""

    earlier: str
    later: str
    doc: str
    by: float = 0.0
    strict: bool = False
    later_in_steps: bool = False

    @property
    def rule(self) -> str:
        later = f"{self.later} x dt" if self.later_in_steps else self.later
        return f"{later} {'>' if self.strict else '>='} {self.earlier}" + (f" + {_fmt(self.by)}" if self.by else "")

    def check(self, config: dict) -> None:
        scale = 1.0 / config["policy_frequency"] if self.later_in_steps else 1.0
        later, earlier = config[self.later], config[self.earlier]
        room = np.min(later) * scale - np.max(earlier)
        if room > self.by if self.strict else room >= self.by - 1e-9:
            return
        in_s = f" (x dt = {_fmt(np.min(later) * scale)} s at its least)" if self.later_in_steps else ""
        raise ValueError(f"config must have {self.rule} for every draw of the ranges ({self.doc}), got "
                         f"{self.later}={_fmt(later)}{in_s} and {self.earlier}={_fmt(earlier)}")


def _fmt(value: Any) -> str:
    if isinstance(value, tuple):
        return "(" + ", ".join(_fmt(v) for v in value) + ")"
    if is_real(value):
        return f"{float(value):g}" if float(value).is_integer() or not np.isfinite(value) else repr(float(value))
    return repr(value)


def _checked_param(key: str, value: Any, param: Param) -> float | int | tuple:
    """``value`` normalized to a float (int for integer parameters) or a ``(lo, hi)`` tuple of them; raises
    ValueError naming ``key`` and the value when it is not a number / a 2-sequence of finite numbers in order
    inside the parameter's interval."""
    if isinstance(value, np.ndarray) and value.ndim == 0:
        value = value.item()
    if is_real(value):
        values = (value,)
    elif isinstance(value, (list, tuple, np.ndarray)) and len(value) == 2 and all(is_real(v) for v in value):
        values = tuple(value)
    else:
        raise ValueError(f"{key} must be a number or a (lo, hi) range of two numbers, got {value!r}")
    shown = _fmt(values if len(values) == 2 else values[0])
    if not all(np.isfinite(v) for v in values):
        raise ValueError(f"{key} must be finite, got {shown}")
    if len(values) == 2 and values[0] > values[1]:
        raise ValueError(f"{key} range (lo, hi) must have lo <= hi, got {shown}")
    for v in values:
        if not param.admits(v):
            raise ValueError(f"{key} must be {param.rule} ({param.doc}), got {shown}")
    cast = int if param.integer else float
    out = tuple(cast(v) for v in values)
    return out if len(out) == 2 else out[0]


def _check_frequencies(config: dict, where: str) -> None:
    for key in ("simulation_frequency", "policy_frequency"):
        v = config[key]
        if not (is_real(v) and float(v).is_integer() and v > 0):
            raise ValueError(f"{key} must be a positive integer [Hz], got {v!r}")
    check_policy_frequency(config["policy_frequency"], where)
    if config["simulation_frequency"] % config["policy_frequency"]:
        raise ValueError(f"simulation_frequency must be an integer multiple of policy_frequency, got "
                         f"{config['simulation_frequency']!r} and {config['policy_frequency']!r}")

