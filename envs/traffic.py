"""highway-env's traffic at array speed, every decision the one highway-env makes (``docs/design.md``, "fast step").

Four fifths of a family's step is highway-env's own ``Road``: ``neighbour_vehicles`` projects every vehicle onto a
lane for every vehicle that asks (IDM for its leader, MOBIL for each side lane and its followers), and ``Road.step``
tests every pair of vehicles for a collision. :class:`FastRoad` keeps both computations and makes them cheaper:

- *neighbours*: while the vehicles act (their positions do not move), each lane's local coordinates of every road
  object are computed once, by highway-env's own ``lane.local_coordinates`` and ``lane.on_lane``, and kept as arrays;
  a vehicle's leader and follower are then selected from those arrays by the same rule highway-env's loop applies
  (the nearest object at or ahead, ties to the last in the road's order; the nearest behind, ties to the first;
  connected lanes searched in highway-env's order, the first lane an object is on counting);
- *collisions*: an array broad phase drops the pairs that highway-env's own spherical pre-check would drop (kept with a
  margin, so a pair near the bound is tested), and highway-env's ``handle_collisions`` runs on the rest, in
  highway-env's order (each vehicle's pairs with the later vehicles, then with the objects), so every flag and every
  impact is set as highway-env sets it. A vehicle whose class changes ``handle_collisions`` or ``_is_colliding`` is
  tested against every other, as highway-env does.

So the episodes are highway-env's, bit for bit (``tests/envs/test_traffic.py`` compares every vehicle at every step
under both cores); ``gym.make(ID, fast_traffic=False)`` builds an env on highway-env's own ``Road``. A road becomes
fast per instance (:func:`make_fast`), never by patching highway-env's classes.

For highway-env's own users, :func:`accelerate` puts a plain highway-env env (any of its nine road ids, with its own
actions, observation and reward) on the same core, one line::

    env = bimp.envs.accelerate(gym.make("highway-v0"))
"""

from __future__ import annotations

import functools
import warnings

import gymnasium as gym
import numpy as np
from highway_env.road.lane import AbstractLane
from highway_env.road.road import LaneIndex, Road
from highway_env.vehicle.objects import Landmark, RoadObject

from bimp.envs.highway.fixed import HIGHWAY_CLASSES

# Up to this many road objects, highway-env's own loops cost less than building the arrays (the paper's three
# vehicles): the fast core steps aside, the same decisions either way.
SMALL_ROAD = 8
# Kept in the broad phase beyond highway-env's pre-check bound [m]: the arrays' distance may differ from
# ``np.linalg.norm``'s in the last bits, and a pair so near the bound is tested exactly by highway-env anyway.
BROAD_PHASE_MARGIN = 1e-6


class _LaneView:
    """Every road object's local coordinates on one lane, as highway-env computes them: ``s`` (M,), ``on`` (M,) bool
    (``lane.on_lane(..., margin=1)``: what ``neighbour_vehicles`` asks)."""

    __slots__ = ("on", "s")

    def __init__(self, lane: AbstractLane, objects: list[RoadObject]):
        s = np.empty(len(objects))
        on = np.zeros(len(objects), dtype=bool)
        for k, obj in enumerate(objects):
            s[k], lateral = lane.local_coordinates(obj.position)
            on[k] = lane.on_lane(obj.position, s[k], lateral, margin=1)
        self.s, self.on = s, on


class FastRoad(Road):
    """highway-env's ``Road`` with its neighbour search and collision checks at array speed (the module doc); the
    same episodes. Built by :func:`make_fast` on any road (highway-env's ``Road`` or a subclass of it)."""

    _acting: list[RoadObject] | None = None  # the objects' order while vehicles act; None outside ``act``
    _base: type = Road  # the road class this one makes fast

    def __reduce_ex__(self, protocol: int):
        # A class made for a road subclass has no name to be found by: pickle the road as its base, made fast again.
        return _unpickle, (self._base,), self.__dict__
    _views: dict[int, _LaneView]
    _rows: dict[int, int]

    def act(self) -> None:
        if len(self.vehicles) + len(self.objects) <= SMALL_ROAD:
            return super().act()
        # Positions are fixed while the vehicles decide: lane coordinates computed once serve every query.
        self._acting = [o for o in self.vehicles + self.objects if not isinstance(o, Landmark)]
        self._rows = {id(o): k for k, o in enumerate(self._acting)}
        self._views = {}
        try:
            super().act()
        finally:
            self._acting = None
            self._views, self._rows = {}, {}

    def _view(self, lane: AbstractLane) -> _LaneView:
        view = self._views.get(id(lane))
        if view is None:
            view = self._views[id(lane)] = _LaneView(lane, self._acting)
        return view

    def neighbour_vehicles(self, vehicle: RoadObject, lane_index: LaneIndex = None) -> tuple:
        """highway-env's ``Road.neighbour_vehicles``, from the lane arrays while vehicles act (else highway-env's)."""
        lane_index = lane_index or vehicle.lane_index
        if self._acting is None or not lane_index:
            return super().neighbour_vehicles(vehicle, lane_index)
        lane = self.network.get_lane(lane_index)
        row = self._rows.get(id(vehicle))
        s = self._view(lane).s[row] if row is not None else lane.local_coordinates(vehicle.position)[0]
        searched = [(lane, 0.0)] + (self._connected(lane_index, lane) if self.neighbour_vehicles_connected_lanes
                                    else [])
        if len(searched) == 1:
            view = self._view(lane)
            found, s_v = view.on.copy(), view.s
        else:
            views = [self._view(search) for search, _ in searched]
            on = np.stack([v.on for v in views])  # (L, M): on which searched lane each object is
            first = on.argmax(axis=0)  # the first lane it is on, as highway-env's loop breaks there
            found = on.any(axis=0)
            columns = np.arange(len(self._acting))
            s_v = np.stack([v.s for v in views])[first, columns] + np.array([o for _, o in searched])[first]
        if row is not None:
            found[row] = False
        ahead, behind = found & (s <= s_v), found & (s_v < s)
        front = rear = None
        if ahead.any():
            nearest = s_v[ahead].min()
            front = self._acting[np.flatnonzero(ahead & (s_v == nearest))[-1]]  # highway-env keeps the last tie
        if behind.any():
            nearest = s_v[behind].max()
            rear = self._acting[np.flatnonzero(behind & (s_v == nearest))[0]]  # and the first tie behind
        return front, rear

    def _connected(self, lane_index: LaneIndex, lane: AbstractLane) -> list[tuple[AbstractLane, float]]:
        """The next and previous lanes ``neighbour_vehicles`` also searches, with their offsets, in its order."""
        _from, _to, _id = lane_index
        out = []
        for next_lanes in self.network.graph.get(_to, {}).values():
            if _id < len(next_lanes):
                out.append((next_lanes[_id], lane.length))
            elif next_lanes:
                out.append((next_lanes[0], lane.length))
        for to_dict in self.network.graph.values():
            if _from in to_dict:
                prev_lanes = to_dict[_from]
                if _id < len(prev_lanes):
                    out.append((prev_lanes[_id], -prev_lanes[_id].length))
                elif prev_lanes:
                    out.append((prev_lanes[0], -prev_lanes[0].length))
        return out

    def step(self, dt: float) -> None:
        """highway-env's ``Road.step``: every vehicle stepped, then ``handle_collisions`` on every pair that
        highway-env's spherical pre-check would not drop, in highway-env's order."""
        vehicles, objects = self.vehicles, self.objects
        if len(vehicles) + len(objects) <= SMALL_ROAD:
            return super().step(dt)
        for vehicle in vehicles:
            vehicle.step(dt)
        others = vehicles + objects
        position = np.array([o.position for o in others], dtype=float)  # (N + K, 2)
        diagonal = np.array([o.diagonal for o in others], dtype=float)
        speed = np.array([v.speed for v in vehicles], dtype=float)
        # highway-env's pre-check for (self i, other j): |p_j - p_i| > (d_i + d_j) / 2 + speed_i * dt drops the pair
        distance = np.linalg.norm(position[None, :, :] - position[: len(vehicles), None, :], axis=-1)  # (N, N + K)
        bound = (diagonal[: len(vehicles), None] + diagonal[None, :]) / 2 + speed[:, None] * dt
        near = ~(distance > bound + BROAD_PHASE_MARGIN)  # as highway-env's "not >": a NaN pair is tested, and raises
        for i, vehicle in enumerate(vehicles):
            if _changes_collisions(type(vehicle)):
                candidates = range(i + 1, len(others))
            else:
                candidates = np.flatnonzero(near[i, i + 1:]) + i + 1
            for j in candidates:
                vehicle.handle_collisions(others[j], dt)


@functools.cache
def _changes_collisions(cls: type) -> bool:
    """Whether ``cls`` changes highway-env's collision test (then every pair of it is tested, as highway-env does)."""
    return (cls.handle_collisions is not RoadObject.handle_collisions
            or cls._is_colliding is not RoadObject._is_colliding)


@functools.cache
def _fast_class(cls: type) -> type:
    """``FastRoad``, or a subclass of ``cls`` (a road class of highway-env's, such as ``RegulatedRoad``) whose
    ``act``, ``step`` and ``neighbour_vehicles`` reach :class:`FastRoad`'s through ``cls``'s own."""
    if cls is Road or cls is FastRoad or issubclass(cls, FastRoad):
        return FastRoad if cls is Road else cls
    return type(f"Fast{cls.__name__}", (cls, FastRoad), {"__module__": __name__, "_base": cls})


def _unpickle(base: type) -> Road:
    return object.__new__(_fast_class(base))


def make_fast(road: Road) -> Road:
    """``road`` turned into its fast counterpart in place (its class, not highway-env's, changes), and returned."""
    if not isinstance(road, Road):
        raise TypeError(f"make_fast expects a highway-env Road, got {type(road).__name__}")
    road.__class__ = _fast_class(type(road))
    return road


def make_fast_if_known(road: Road) -> Road:
    """``road`` made fast when every vehicle class on it is known not to move anything while vehicles act
    (:func:`_known`); else left on highway-env's own code (a user's ``other_vehicles_type``): the same episodes."""
    return road if _unknown_classes(road) else make_fast(road)


# --- highway-env's own envs ------------------------------------------------------------------------------------
def _known(cls: type) -> bool:
    """A vehicle class whose ``act`` moves nothing (highway-env's own and bimp's, each episode of which the sameness
    tests compare): the neighbour arrays of one ``act`` then stand for the whole of it."""
    return cls.__module__.startswith(("highway_env.", "bimp.envs."))


def _unknown_classes(road: Road) -> list[str]:
    return sorted({f"{type(o).__module__}.{type(o).__qualname__}" for o in road.vehicles + road.objects
                   if not _known(type(o))})


class FastTraffic(gym.Wrapper):
    """A highway-env env on the fast core: its road made fast now and at every reset (:func:`accelerate`)."""

    def __init__(self, env: gym.Env):
        super().__init__(env)
        make_fast(env.unwrapped.road)

    def reset(self, **kwargs):
        out = self.env.reset(**kwargs)
        road = self.env.unwrapped.road
        unknown = _unknown_classes(road)
        if unknown:  # a config that brought another class: this episode on highway-env's own road, said once
            warnings.warn(f"accelerate: vehicle classes {unknown} are not known to move nothing while vehicles "
                          "act: this episode runs on highway-env's own Road", stacklevel=2)
        else:
            make_fast(road)
        return out


def accelerate(env: gym.Env) -> gym.Env:
    """``env``, a highway-env env (``gym.make("highway-v0")`` or any of the nine road ids bimp drives), with its
    traffic on the fast core: the same trajectories, several times fewer seconds (``docs/highway-env.md``). Its
    actions, observation, reward and config stay highway-env's. ``ValueError`` naming what it cannot speed up
    exactly (another env, a vehicle class it does not know), the env left as it was."""
    if isinstance(env, FastTraffic):
        return env
    base = getattr(env, "unwrapped", None)
    kinds = tuple(HIGHWAY_CLASSES.values())
    if not isinstance(base, kinds) or not isinstance(getattr(base, "road", None), Road):
        raise ValueError(f"accelerate takes a highway-env env of one of {sorted(HIGHWAY_CLASSES)}, got "
                         f"{type(base).__name__}: its traffic code is not known to be the one this core reproduces")
    unknown = _unknown_classes(base.road)
    if unknown:
        raise ValueError(f"accelerate: vehicle classes {unknown} are not highway-env's or bimp's: whether they move "
                         "while vehicles act is not known, so the fast core cannot promise the same episodes")
    return FastTraffic(env)


__all__ = ["BROAD_PHASE_MARGIN", "SMALL_ROAD", "FastRoad", "FastTraffic", "accelerate", "make_fast",
           "make_fast_if_known"]
