"""What every scenario family of the suite shares: its difficulty, its ranges, its draws, and what the adapter reads.

A family is a highway-env env class (a subclass of one of highway-env's, as exit-v0 and the others are) with
:class:`Family` before highway-env's class in its bases (:class:`HighwayFamily` for a family on highway-env's
``HighwayEnv`` road: its population keys, ``lanes_count`` and the EV's placement besides). The mixin gives it:

- a ``difficulty`` config key (``"easy"``, ``"medium"``, ``"hard"``, or whatever names the family's
  :attr:`Family.DIFFICULTIES` holds) that sets every randomized range at once, and one config key per range
  (``(lo, hi)``, drawn uniformly at every reset; a number fixes it) that overrides that range. A key given with
  ``difficulty`` in the same ``configure`` (``gym.make(..., config=...)``, ``reset(options={"config": ...})``)
  overrides the preset; a ``difficulty`` given alone resets every range to its preset;
- the ranges checked as a frozen dataclass (:attr:`Family.RANGES`, each family's own): each range inside the
  family's documented envelope (:func:`check_ranges`) and whatever else the family's oracle needs (its
  ``__post_init__``). A difficulty, a range or a config key outside what the oracle covers raises ``ValueError``
  (:class:`bimp.configs.ConfigError` for a value) naming it, before anything is simulated;
- highway-env's config keys the family replaces by its own draws (:attr:`Family.REMOVED_KEYS`: highway-v0's
  ``vehicles_count``, ``vehicles_density`` ...) refused as unknown, so that no key is silently ignored;
- the draws from the env's own ``np_random`` (seeded by ``reset(seed=...)``), recorded in ``drawn_params`` as the
  paper's envs record theirs (the evaluation's records carry them);
- what the adapter needs per family (:mod:`bimp.envs.highway.profiles`'s ``Profile``): ``BOUNDS``,
  ``ACTUATOR_STEER``, ``TARGET_SPEED``, ``DURATION``, ``OVERTAKE``, so that a family is one module plus one entry
  in the suite's table (:data:`bimp.envs.suite.FAMILIES`).
"""

from __future__ import annotations

import dataclasses
import numbers
from collections.abc import Mapping
from typing import Any, ClassVar

from highway_env.vehicle.behavior import AggressiveVehicle, DefensiveVehicle, IDMVehicle, LinearVehicle
from highway_env.vehicle.kinematics import Vehicle

from bimp.configs import ConfigError
from bimp.envs.scene import ACTUATOR_STEER, Bounds

EV_X = 200.0  # m: the EV's start along a family's road, room for the traffic behind it
EV_COLOUR = (50, 200, 0)  # green, as the paper's EV: highway-env draws a plain Vehicle yellow, as Linear traffic
MIN_TRAFFIC_GAP = 15.0  # m, centre to centre: a car (5 m) and IDM's jam distance (DISTANCE_WANTED 10 m less a car)
GAP_JITTER = (0.7, 1.3)  # each centre gap is 1000 / density m times a factor uniform in this range


@dataclasses.dataclass(frozen=True)
class Envelope:
    """Where one range of a family may lie: ``low <= lo <= hi <= high`` in ``unit``; ``why``: what bounds it."""

    low: float
    high: float
    unit: str
    why: str


def check_ranges(ranges: Any, envelope: Mapping[str, Envelope]) -> None:
    """Every ``(lo, hi)`` field of the frozen dataclass ``ranges`` ordered and inside its :class:`Envelope`;
    :class:`bimp.configs.ConfigError` naming the first field that is not. Call after ``check_fields``."""
    for field in dataclasses.fields(ranges):
        lo, hi = getattr(ranges, field.name)
        e = envelope[field.name]
        if not e.low <= lo <= hi <= e.high:
            within = f"a range (lo, hi) with {e.low:g} <= lo <= hi <= {e.high:g} {e.unit}".rstrip()
            raise ConfigError(field.name, within, (lo, hi), e.why)


def check_shares(ranges: Any) -> None:
    """The ``aggressive_share`` and ``defensive_share`` ranges of ``ranges`` (probabilities of one traffic vehicle's
    kind) with highs summing to at most 1; :class:`bimp.configs.ConfigError` naming ``defensive_share`` otherwise."""
    if ranges.aggressive_share[1] + ranges.defensive_share[1] > 1.0:
        raise ConfigError("defensive_share", f"a range whose high is at most 1 - aggressive_share's high "
                          f"({1.0 - ranges.aggressive_share[1]:g})", ranges.defensive_share, "the shares are "
                          "probabilities of one vehicle's kind")


def check_leader_gap(ranges: Any, gap: float, d_min: float, leader: str) -> None:
    """The ``leader_gap`` range of ``ranges`` (with ``ev_speed`` and ``traffic_speed``) refused where ``gap`` [m],
    the oracle's least footprint gap at the worst corner behind a leader braking as ``leader`` says, is below
    ``d_min`` [m]: :class:`bimp.configs.ConfigError` naming ``leader_gap`` and the low that would do (the least gap
    grows 1:1 with the leader's distance)."""
    if gap < d_min:
        need = ranges.leader_gap[0] + d_min - gap
        raise ConfigError("leader_gap", f"a range whose low is at least {need:.1f} m with ev_speed up to "
                          f"{ranges.ev_speed[1]:g} m/s and traffic_speed from {ranges.traffic_speed[0]:g} m/s",
                          ranges.leader_gap, f"outside the oracle's cover: braking at the planning bounds from the "
                          f"first step behind a leader {leader} comes within {gap:.2f} m of it, d_min is {d_min:g} m")


def with_difficulty(env: Any, config: Mapping | None, difficulty: str | None) -> Mapping | None:
    """The constructor's ``config`` of a family env made at one ``difficulty`` (the ``-easy``/``-hard`` ids:
    ``bimp/cut-in-hard-v0``): that difficulty kept on ``env`` as ``fixed_difficulty`` and put under ``config``'s own
    keys, so that :func:`check_fixed_difficulty` refuses another one at ``gym.make`` and at every later reset (a
    non-mapping config is left for the env to refuse)."""
    env.fixed_difficulty = difficulty
    if difficulty is None or not (config is None or isinstance(config, Mapping)):
        return config
    return {"difficulty": difficulty, **(config or {})}


def check_fixed_difficulty(env: Any, difficulty: Any) -> None:
    """:class:`bimp.configs.ConfigError` naming ``difficulty`` where ``env`` was made at another one
    (:func:`with_difficulty`): an id that names a difficulty never runs another's episodes."""
    fixed = getattr(env, "fixed_difficulty", None)
    if fixed is not None and difficulty != fixed:
        raise ConfigError("difficulty", f"{fixed!r}, the difficulty this id names", difficulty,
                          f"gym.make('bimp/{env.NAME}-v0', config={{'difficulty': ...}}) takes any")


def _as_range(value: Any) -> Any:
    # A number fixes a range (as the paper's envs take one); anything else is left to check_fields to judge.
    if isinstance(value, numbers.Real) and not isinstance(value, bool):
        return (value, value)
    return value


def traffic_kind(vehicle: Vehicle) -> str:
    """``"aggressive"``, ``"defensive"`` or ``"idm"``: the kind of a traffic vehicle (:meth:`Family._place_traffic`)."""
    return ("aggressive" if isinstance(vehicle, AggressiveVehicle) else "defensive"
            if isinstance(vehicle, DefensiveVehicle) else "idm")


class Family:
    """The mixin of every suite family (module docstring). A family class sets the class attributes below; the
    concrete ones (with a ``NAME``) are checked when the class is made."""

    NAME: ClassVar[str] = ""  # the scenario's name in every command (--scenario stalled-vehicle)
    ID: ClassVar[str] = ""  # its key in the adapter's tables, registered as bimp/ID
    DURATION: ClassVar[float] = 0.0  # s: the episode's time limit (highway-env's duration, the registration's steps)
    TARGET_SPEED: ClassVar[float] = 0.0  # m/s: the behaviour layer's free-road target speed
    BOUNDS: ClassVar[Bounds] = Bounds()  # the planning bounds (the paper's: straight roads)
    ACTUATOR_STEER: ClassVar[tuple[float, float]] = ACTUATOR_STEER  # rad: what the normalized steering maps onto
    RANGES: ClassVar[type]  # the family's frozen dataclass of (lo, hi) ranges
    DIFFICULTIES: ClassVar[Mapping[str, Any]] = {}  # difficulty -> RANGES instance
    DEFAULT_DIFFICULTY: ClassVar[str] = "medium"
    REMOVED_KEYS: ClassVar[frozenset[str]] = frozenset()  # highway-env keys the family's own draws replace
    # highway-env keys the family checks itself, more strictly than the adapter would (bimp.envs.checks)
    CHECKED_KEYS: ClassVar[frozenset[str]] = frozenset({"duration"})
    OVERTAKE: ClassVar[bool] = False  # the behaviour layer overtakes through the oncoming lane (two-way-overtake)

    drawn_params: dict[str, Any]
    fixed_difficulty: str | None = None  # the difficulty the id names (bimp/cut-in-hard-v0), else None

    def __init__(self, config: Mapping | None = None, render_mode: str | None = None,
                 difficulty: str | None = None) -> None:
        super().__init__(config=with_difficulty(self, config, difficulty), render_mode=render_mode)

    def __init_subclass__(cls, **kwargs) -> None:
        super().__init_subclass__(**kwargs)
        if not cls.NAME:
            return
        problems = [f"{key} is not set" for key in ("ID", "DURATION", "TARGET_SPEED") if not getattr(cls, key)]
        if cls.DEFAULT_DIFFICULTY not in cls.DIFFICULTIES:
            problems.append(f"DEFAULT_DIFFICULTY {cls.DEFAULT_DIFFICULTY!r} is not among {list(cls.DIFFICULTIES)}")
        problems += [f"difficulty {name!r} is not a {cls.RANGES.__name__}"
                     for name, preset in cls.DIFFICULTIES.items() if not isinstance(preset, cls.RANGES)]
        if problems:
            raise TypeError(f"family {cls.NAME!r} ({cls.__name__}): {'; '.join(problems)}")

    @classmethod
    def range_keys(cls) -> tuple[str, ...]:
        """The config keys of the family's ranges (the fields of :attr:`RANGES`)."""
        return tuple(f.name for f in dataclasses.fields(cls.RANGES))

    @classmethod
    def default_config(cls) -> dict:
        config = super().default_config()
        for key in cls.REMOVED_KEYS:
            config.pop(key, None)
        config.update(duration=cls.DURATION, difficulty=cls.DEFAULT_DIFFICULTY,
                      **dataclasses.asdict(cls.DIFFICULTIES[cls.DEFAULT_DIFFICULTY]))
        return config

    def configure(self, config: Mapping | None) -> None:
        """highway-env's ``configure`` (the config every later reset starts from), after checking ``config``: unknown
        keys, the difficulty and the resulting ranges (module docstring); ``ValueError`` naming the key."""
        if config is not None and not isinstance(config, Mapping):
            raise ValueError(f"{self.NAME}: config must be a mapping of config keys (a dict), got {config!r}")
        config = dict(config or {})
        unknown = sorted(set(config) - set(self.default_config()))
        if unknown:
            replaced = sorted(set(unknown) & self.REMOVED_KEYS)
            why = f" ({replaced} are highway-env's, replaced by the family's own draws)" if replaced else ""
            raise ValueError(f"{self.NAME}: unknown config key(s) {unknown}{why}; the family's keys are "
                             f"{['difficulty', *self.range_keys()]}, besides highway-env's own")
        if "duration" in config and config["duration"] != self.DURATION:
            # The registration's step limit is DURATION: a longer one would be cut there without a word.
            raise ConfigError("duration", f"{self.DURATION:g} (s)", config["duration"],
                              f"{self.NAME}'s episodes are registered with a {self.DURATION:g} s step limit")
        difficulty = config.get("difficulty", self.config["difficulty"])
        check_fixed_difficulty(self, difficulty)
        if not isinstance(difficulty, str) or difficulty not in self.DIFFICULTIES:
            raise ConfigError("difficulty", f"one of {', '.join(map(repr, self.DIFFICULTIES))}", difficulty,
                              f"the difficulties {self.NAME}'s oracle covers")
        base = (dataclasses.asdict(self.DIFFICULTIES[difficulty]) if "difficulty" in config
                else {k: self.config[k] for k in self.range_keys()})
        given = {k: _as_range(config[k]) for k in self.range_keys() if k in config}
        ranges = self.RANGES(**{**base, **given})  # checks every range: ConfigError naming it
        super().configure({**config, **dataclasses.asdict(ranges)})

    def _reset(self) -> None:
        self.drawn_params = {}
        super()._reset()

    def _place_traffic(self, lanes: list, start: float, end: float, density: float, aggressive: float,
                       defensive: float, skip: tuple[int, ...] = (), keep_out: Mapping | None = None) -> None:
        """Traffic on ``lanes`` (a road's lanes, by index) from ``start`` to ``end`` [m along them]: one vehicle every
        ``1000 / density`` m (``density`` per km per lane) times a factor in :data:`GAP_JITTER`, at least
        :data:`MIN_TRAFFIC_GAP` apart, from a uniform offset; each an ``AggressiveVehicle``, ``DefensiveVehicle``
        or ``IDMVehicle`` with probabilities ``aggressive``, ``defensive`` and the rest, at a speed drawn from the
        config's ``traffic_speed``. No traffic, and no draws, on the lanes in ``skip``; on lane ``k`` none starts in
        ``keep_out[k]``'s stretches ``[(from, to), ...)`` (drawn all the same, so the draws do not depend on them).
        The kinds' counts go to ``drawn_params`` (``traffic_idm`` ...). Every draw from the env's ``np_random``."""
        counts = {"idm": 0, "aggressive": 0, "defensive": 0}
        for k, lane in enumerate(lanes):
            if density <= 0.0:
                break
            if k in skip:
                continue
            spacing = 1000.0 / density
            x = start + float(self.np_random.uniform(0.0, spacing))
            while x <= end:
                place = not any(lo <= x < hi for lo, hi in (keep_out or {}).get(k, ()))
                vehicle = self._traffic_vehicle(lane, x, aggressive, defensive, place=place)
                if vehicle is not None:
                    counts[traffic_kind(vehicle)] += 1
                x += max(MIN_TRAFFIC_GAP, spacing * float(self.np_random.uniform(*GAP_JITTER)))
        self.drawn_params.update({f"traffic_{kind}": n for kind, n in counts.items()})

    def _traffic_vehicle(self, lane, x: float, aggressive: float, defensive: float,
                         place: bool = True) -> Vehicle | None:
        """One traffic vehicle of :meth:`_place_traffic` at ``x`` [m along ``lane``]: its kind (``AggressiveVehicle``,
        ``DefensiveVehicle`` or ``IDMVehicle`` with probabilities ``aggressive``, ``defensive`` and the rest) and its
        speed (from the config's ``traffic_speed``, its target) drawn; put on the road and returned where ``place``,
        else None (drawn all the same)."""
        u = float(self.np_random.uniform())
        kind = AggressiveVehicle if u < aggressive else DefensiveVehicle if u < aggressive + defensive else IDMVehicle
        speed = float(self.np_random.uniform(*self.config["traffic_speed"]))
        if not place:
            return None
        vehicle = kind(self.road, lane.position(x, 0.0), lane.heading_at(x), speed)
        if isinstance(vehicle, LinearVehicle):
            # highway-env's randomize_behavior would redraw the very parameters that make a vehicle aggressive or
            # defensive; and their data log (for fitting) only costs time here.
            vehicle.collecting_data = False
        else:
            vehicle.randomize_behavior()
        self.road.vehicles.append(vehicle)
        return vehicle

    def _add_ev(self, lane, speed: float):
        """The EV (the action type's vehicle, drawn :data:`EV_COLOUR`) at :data:`EV_X` on ``lane`` at ``speed``
        [m/s], as the controlled vehicle and on the road; returned."""
        ev = self.action_type.vehicle_class(self.road, lane.position(EV_X, 0.0), lane.heading_at(EV_X), speed)
        ev.color = EV_COLOUR
        self.controlled_vehicles = [ev]
        self.road.vehicles.append(ev)
        return ev

    def _draw(self, key: str) -> float:
        """This episode's value of the range ``key`` [its unit], uniform on the config's ``(lo, hi)`` from the env's
        ``np_random``; recorded in ``drawn_params``."""
        lo, hi = self.config[key]
        value = float(self.np_random.uniform(lo, hi))
        self.drawn_params[key] = value
        return value


class HighwayFamily(Family):
    """A family on highway-env's ``HighwayEnv`` road (bases ``(HighwayFamily, HighwayEnv)``) with its own
    population: highway-env's population keys refused (:attr:`REMOVED_KEYS`), ``lanes_count`` 3 by default and an
    int in [2, 5] (``LANES_WHY``: what the family needs the lane beside the EV's for)."""

    REMOVED_KEYS = frozenset({"vehicles_count", "vehicles_density", "initial_lane_id", "ego_spacing",
                              "other_vehicles_type", "controlled_vehicles"})
    CHECKED_KEYS = Family.CHECKED_KEYS | {"lanes_count"}
    LANES_WHY: ClassVar[str] = "a lane beside the EV's"

    @classmethod
    def default_config(cls) -> dict:
        config = super().default_config()
        config.update(lanes_count=3)
        return config

    def configure(self, config: Mapping | None) -> None:
        if isinstance(config, Mapping) and "lanes_count" in config:  # a None given is refused too
            lanes = config["lanes_count"]
            if isinstance(lanes, bool) or not isinstance(lanes, int) or not 2 <= lanes <= 5:
                raise ConfigError("lanes_count", "an int in [2, 5]", lanes, self.LANES_WHY)
        super().configure(config)
