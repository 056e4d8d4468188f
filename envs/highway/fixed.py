"""highway-env's envs as the adapter runs them: continuous actions on a routed EV, and four rewards that work.

Every supported env runs as a subclass made by :func:`adapted_class` (``Bimp`` + highway-env's class name): the
:class:`AdaptedEnv` mixin before highway-env's class, never a change to highway-env's own classes (no global
monkey-patch). The mixin:

- drives the EV by highway-env's :class:`ContinuousAction` as ``config["action"]`` gives it, with a
  :class:`RoutedVehicle` as the EV: highway-env's plain kinematic ``Vehicle`` plus ``route`` and
  ``plan_route_to``, so the envs that plan the EV's route (roundabout to ``nxs``, u-turn to ``d``, intersection to
  its ``destination``, drawn from ``np_random`` when unset) keep it; under continuous actions highway-env's EV is a
  plain ``Vehicle`` whose ``plan_route_to`` raises an ``AttributeError`` that the envs swallow, and the route is lost;
- gives the EV a route where highway-env's env names none (``DESTINATION``: exit-v0's exit);
- replaces highway-env's observation by :class:`NoObservation` (the adapter computes bimp's own; highway-env's
  ``TimeToCollision`` observation of two-way and u-turn needs the discrete action's ``target_speeds``).

Where highway-env fails under continuous actions, the subclass below fixes it, saying what was broken and the reward
it uses instead.
"""

from __future__ import annotations

import numpy as np
from gymnasium import spaces
from highway_env import utils
from highway_env.envs.common.action import ContinuousAction
from highway_env.envs.common.observation import ObservationType
from highway_env.envs.exit_env import ExitEnv
from highway_env.envs.highway_env import HighwayEnv, HighwayEnvFast
from highway_env.envs.intersection_env import IntersectionEnv
from highway_env.envs.merge_env import MergeEnv
from highway_env.envs.racetrack_env import RacetrackEnv
from highway_env.envs.roundabout_env import RoundaboutEnv
from highway_env.envs.two_way_env import TwoWayEnv
from highway_env.envs.u_turn_env import UTurnEnv
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.controller import ControlledVehicle, MDPVehicle
from highway_env.vehicle.kinematics import Vehicle


class RoutedVehicle(Vehicle):
    """highway-env's kinematic ``Vehicle`` (what ``ContinuousAction`` drives) that keeps a route: ``route`` (a list
    of lane indices, None for none) and ``plan_route_to`` (highway-env's own, :class:`ControlledVehicle`'s)."""

    route = None
    plan_route_to = ControlledVehicle.plan_route_to

    def step(self, dt: float) -> None:
        # Never in reverse: highway-env's Vehicle brakes through 0 into reverse (MIN_SPEED = -40 m/s); bimp's EV
        # stops at 0, as the paper's EV does and as the planners' vehicle model (trained with that clamp) predicts.
        super().step(dt)
        self.speed = max(self.speed, 0.0)


class RoutedContinuousAction(ContinuousAction):
    """highway-env's ``ContinuousAction`` whose EV is a :class:`RoutedVehicle`."""

    @property
    def vehicle_class(self):
        if self.dynamical:
            return super().vehicle_class
        return RoutedVehicle


class NoObservation(ObservationType):
    """highway-env's observation switched off (one zero): the adapter publishes bimp's observation instead, and
    highway-env's own would only cost time (``Kinematics`` builds a pandas frame per step)."""

    def space(self) -> spaces.Space:
        return spaces.Box(0.0, 0.0, shape=(1,), dtype=np.float32)

    def observe(self) -> np.ndarray:
        return np.zeros(1, dtype=np.float32)


# The traffic classes' driver parameters as highway-env defines them, read when this module loads (before any env
# of the process is made through it). See AdaptedEnv._reset.
def _driver_classes(cls: type = IDMVehicle) -> list[type]:
    """``IDMVehicle`` and its subclasses (AggressiveVehicle, DefensiveVehicle, LinearVehicle ...): intersection-v0
    writes onto whichever of them its config's ``other_vehicles_type`` names."""
    return [cls, *(sub for child in cls.__subclasses__() for sub in _driver_classes(child))]


_TRAFFIC_DEFAULTS = {cls: {k: v for k, v in vars(cls).items() if k.isupper()}
                     for cls in _driver_classes()}


class AdaptedEnv:
    """The mixin every adapted env puts before highway-env's class (see the module docstring)."""

    DESTINATION: str | None = None  # the EV's destination node where highway-env's env plans none

    def define_spaces(self) -> None:
        options = {k: v for k, v in self.config["action"].items() if k not in ("type", "target_speeds")}
        self.observation_type = NoObservation(self)
        self.action_type = RoutedContinuousAction(self, **options)
        self.observation_space = self.observation_type.space()
        self.action_space = self.action_type.space()

    def _reset(self) -> None:
        # intersection-v0 writes its traffic's IDM parameters onto the vehicle class itself (DISTANCE_WANTED,
        # COMFORT_ACC_MAX, COMFORT_ACC_MIN), for every env of the process made after it: the traffic and the
        # behaviour layer of a highway-v0 episode depended on whether an intersection had run before it in the same
        # worker. Every adapted env starts from highway-env's own values; intersection-v0 then sets its own again.
        for cls, values in _TRAFFIC_DEFAULTS.items():
            for key in [k for k in vars(cls) if k.isupper() and k not in values]:
                delattr(cls, key)  # written onto a subclass that inherited it: the inherited value shows again
            for key, value in values.items():
                setattr(cls, key, value)
        super()._reset()
        ev = self.vehicle
        if self.DESTINATION and isinstance(ev, RoutedVehicle) and not ev.route:
            ev.plan_route_to(self.DESTINATION)

    def _lane_changed(self) -> float:
        """1.0 at a step that took the EV to another lane of its road (the continuous counterpart of highway-env's
        discrete LANE_LEFT / LANE_RIGHT actions, which its rewards count), else 0.0."""
        lane = self.vehicle.lane_index
        previous, self._last_lane = getattr(self, "_last_lane", lane), lane
        return float(previous[:2] == lane[:2] and previous[2] != lane[2])


class FixedMergeEnv(AdaptedEnv, MergeEnv):
    """merge-v0 under continuous actions. Broken: its ``_rewards`` scores a lane change as ``action in [0, 2]`` (the
    discrete LANE_LEFT / LANE_RIGHT), which raises ``ValueError: The truth value of an array ... is ambiguous`` for
    an array action (at the first reset). Reward here: highway-env's merge reward (its weights, normalization and
    terms: collision, right lane, high speed, the altruistic merging-speed penalty) with ``lane_change_reward`` = 1
    at a step where the EV reached another lane of its road (:meth:`AdaptedEnv._lane_changed`), else 0."""

    def _rewards(self, action) -> dict[str, float]:
        scaled_speed = utils.lmap(self.vehicle.speed, self.config["reward_speed_range"], [0, 1])
        return {
            "collision_reward": self.vehicle.crashed,
            "right_lane_reward": self.vehicle.lane_index[2] / 1,
            "high_speed_reward": scaled_speed,
            "lane_change_reward": self._lane_changed(),
            "merging_speed_reward": sum(
                (v.target_speed - v.speed) / v.target_speed for v in self.road.vehicles
                if v.lane_index == ("b", "c", 2) and isinstance(v, ControlledVehicle)),
        }


class FixedRoundaboutEnv(AdaptedEnv, RoundaboutEnv):
    """roundabout-v0 under continuous actions. Broken: as merge-v0, ``lane_change_reward`` is ``action in [0, 2]``
    (``ValueError ... truth value of an array is ambiguous`` at reset). Reward here: highway-env's roundabout reward
    (collision, high speed as the index of the EV's speed among ``MDPVehicle``'s target speeds, on-road factor,
    normalization) with ``lane_change_reward`` = 1 at a step where the EV reached another lane of its road."""

    def _rewards(self, action) -> dict[str, float]:
        return {
            "collision_reward": self.vehicle.crashed,
            "high_speed_reward": MDPVehicle.get_speed_index(self.vehicle)
            / (MDPVehicle.DEFAULT_TARGET_SPEEDS.size - 1),
            "lane_change_reward": self._lane_changed(),
            "on_road_reward": self.vehicle.on_road,
        }


class FixedTwoWayEnv(AdaptedEnv, TwoWayEnv):
    """two-way-v0 under continuous actions. Broken: its ``_rewards`` reads the EV's ``speed_index``,
    ``target_speeds`` and ``target_lane_index`` (a discrete-action ``MDPVehicle``'s), and its ``TimeToCollision``
    observation the ``target_speeds`` too: ``AttributeError: 'Vehicle' object has no attribute 'target_speeds'``.
    Reward here: highway-env's weights (``high_speed_reward`` 0.8, ``left_lane_reward`` 0.2) on the speed mapped
    linearly from ``MDPVehicle``'s target speeds (20..30 m/s) onto [0, 1], clipped, and on the EV's current lane
    (its index among the lanes of its direction, the left one counting 1, as highway-env's ``target_lane_index``
    term)."""

    def _rewards(self, action) -> dict[str, float]:
        neighbours = self.road.network.all_side_lanes(self.vehicle.lane_index)
        speeds = MDPVehicle.DEFAULT_TARGET_SPEEDS
        return {
            "high_speed_reward": float(np.clip(utils.lmap(self.vehicle.speed, [speeds[0], speeds[-1]], [0, 1]), 0, 1)),
            "left_lane_reward": (len(neighbours) - 1 - self.vehicle.lane_index[2]) / max(len(neighbours) - 1, 1),
        }


class FixedUTurnEnv(AdaptedEnv, UTurnEnv):
    """u-turn-v0 under continuous actions. Broken: its ``TimeToCollision`` observation reads the EV's
    ``target_speeds`` (a discrete-action ``MDPVehicle``'s): ``AttributeError: 'Vehicle' object has no attribute
    'target_speeds'`` at reset. Fixed by :class:`AdaptedEnv`'s observation (the adapter publishes bimp's). Reward:
    highway-env's u-turn reward unchanged (collision, left lane, high speed over ``reward_speed_range``, on-road
    factor, normalization), which reads only the EV's speed, lane and state."""


_FIXED = {MergeEnv: FixedMergeEnv, RoundaboutEnv: FixedRoundaboutEnv, TwoWayEnv: FixedTwoWayEnv,
          UTurnEnv: FixedUTurnEnv}
_ADAPTED: dict[type, type] = {}


class ExitDestination:
    """exit-v0's EV takes the exit (``_is_success``: the exit lane ``("2", "exit", 0)``): its route goes there."""

    DESTINATION = "exit"


def adapted_class(cls: type) -> type:
    """The adapted subclass of highway-env's env class ``cls``: a fixed one above for the four that fail under
    continuous actions, else ``Bimp<Name>`` = (:class:`AdaptedEnv`, ``cls``), made once and cached. A subclass of one
    of the four (a suite family on two-way-v0's road) takes its fix: (``Fixed...``, ``cls``), and keeps its own
    ``_rewards`` where it defines one (its task's reward, not the road's)."""
    if cls in _FIXED:
        return _FIXED[cls]
    if cls not in _ADAPTED:
        fixed = next((_FIXED[base] for base in cls.__mro__ if base in _FIXED), None)
        bases = ((fixed, cls) if fixed is not None else (ExitDestination, AdaptedEnv, cls)
                 if issubclass(cls, ExitEnv) else (AdaptedEnv, cls))
        own = {"_rewards": vars(cls)["_rewards"]} if fixed is not None and "_rewards" in vars(cls) else {}
        _ADAPTED[cls] = type(f"Bimp{cls.__name__}", bases, {"__module__": __name__, **own})
    return _ADAPTED[cls]


# highway-env's classes behind the supported ids (what gym.make(ID) builds).
HIGHWAY_CLASSES = {
    "highway-v0": HighwayEnv, "highway-fast-v0": HighwayEnvFast, "merge-v0": MergeEnv, "exit-v0": ExitEnv,
    "roundabout-v0": RoundaboutEnv, "two-way-v0": TwoWayEnv, "u-turn-v0": UTurnEnv, "racetrack-v0": RacetrackEnv,
    "intersection-v0": IntersectionEnv,
}
