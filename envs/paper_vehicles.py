"""The paper envs' vehicles, with highway-env's collision handling switched off (the env decides contacts from the
footprint gap itself), and the lanes of their road."""

from __future__ import annotations

import numpy as np
from highway_env.road.lane import CircularLane, LineType, StraightLane
from highway_env.road.road import RoadNetwork
from highway_env.vehicle.controller import ControlledVehicle
from highway_env.vehicle.kinematics import Vehicle

from bimp.envs.road import RoadGeometry


# --- vehicles ------------------------------------------------------------------------------------------------------
class _FootprintContact:
    """highway-env's collision handling switched off: the env decides contacts from the footprint gap itself.

    highway-env's ``Road.step`` calls ``handle_collisions`` for every pair; when the pair *will* intersect within
    the step at constant velocity it stores an ``impact`` translation (the separating vector, half to each) that
    the next ``Vehicle.step`` adds to the position, and it sets ``crashed``; a crashed vehicle then has its input
    overridden (steering 0, braking to a stop). All three would change the recorded motion. Here vehicles are not
    collidable, ``handle_collisions`` does nothing, and ``crashed`` (which the env sets, so highway-env draws the
    contact) never changes the dynamics.
    """

    def _no_collision_handling(self) -> None:
        self.collidable = False
        self.impact = None

    def handle_collisions(self, other, dt: float = 0.0) -> None:
        return None

    @classmethod
    def create_from(cls, vehicle) -> Vehicle:
        """A plain snapshot, for highway-env's trajectory history (``show_trajectories``); highway-env's own
        ``ControlledVehicle.create_from`` passes arguments ``ObstacleVehicle`` does not take."""
        snapshot = Vehicle(vehicle.road, vehicle.position, vehicle.heading, vehicle.speed)
        snapshot.crashed = vehicle.crashed
        if getattr(vehicle, "color", None):
            snapshot.color = vehicle.color
        return snapshot

    def clip_actions(self) -> None:
        crashed, self.crashed = self.crashed, False
        try:
            super().clip_actions()
        finally:
            self.crashed = crashed


class EgoVehicle(_FootprintContact, Vehicle):
    """highway-env's kinematic bicycle with the speed clamped at >= 0 (highway-env lets braking reverse)."""

    MIN_SPEED = 0.0

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._no_collision_handling()

    def step(self, dt: float) -> None:
        super().step(dt)
        self.speed = max(self.speed, 0.0)


class ObstacleVehicle(_FootprintContact, ControlledVehicle):
    """An OV that keeps its lane centre (highway-env's lateral controller) and follows a scripted
    acceleration: zero, or ``-decel`` from ``brake_onset`` seconds until it stands still (``decel`` is a
    magnitude, m/s^2)."""

    def __init__(self, road, position, heading, speed, lane_index, brake_onset=np.inf, decel=0.0):
        super().__init__(road, position, heading, speed, target_lane_index=lane_index, target_speed=speed)
        self.brake_onset, self.decel, self.clock, self.acceleration = brake_onset, decel, 0.0, 0.0
        self._no_collision_handling()

    def act(self, action=None) -> None:
        self.follow_road()
        braking = self.clock >= self.brake_onset and self.speed > 0.0
        Vehicle.act(self, {"steering": self.steering_control(self.target_lane_index),
                           "acceleration": -self.decel if braking else 0.0})

    def step(self, dt: float) -> None:
        v0 = self.speed
        super().step(dt)
        self.speed = max(self.speed, 0.0)
        self.clock += dt
        self.acceleration = (self.speed - v0) / dt


def _build_network(road: RoadGeometry, speed_limit: float) -> RoadNetwork:
    """highway-env lanes tracing :class:`RoadGeometry` (straight a->b, arc b->c, straight c->d)."""
    net = RoadNetwork()
    sigma = 1.0 if road.arc_angle >= 0 else -1.0
    s1, s2 = road.straight_in, road.straight_in + road.arc_length
    for i in range(road.lanes):
        c = float(road.lane_offset(i))
        lines = [LineType.CONTINUOUS_LINE if i == 0 else LineType.NONE,
                 LineType.CONTINUOUS_LINE if i == road.lanes - 1 else LineType.STRIPED]
        kw = dict(width=road.lane_width, line_types=lines, speed_limit=speed_limit)
        net.add_lane("a", "b", StraightLane(road.position(0.0, c), road.position(s1, c), **kw))
        if road.arc_length > 0:
            phase = -sigma * np.pi / 2
            # CONTINUOUS_LINE is drawn as one straight stroke: curves need the dashed-without-gaps kind.
            arc_lines = [LineType.CONTINUOUS if t == LineType.CONTINUOUS_LINE else t for t in lines]
            arc = CircularLane(road._centre, road.radius - sigma * c, phase, phase + road.arc_angle,
                               clockwise=sigma > 0, **{**kw, "line_types": arc_lines})
            net.add_lane("b", "c", arc)
        else:
            net.add_lane("b", "c", StraightLane(road.position(s1, c), road.position(s2 + 1e-3, c), **kw))
        net.add_lane("c", "d", StraightLane(road.position(s2, c), road.position(road.length, c), **kw))
    return net


