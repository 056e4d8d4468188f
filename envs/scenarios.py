"""The paper's two scenarios (section V) as highway-env environments.

Both share :class:`BimpEnv`: a two-lane road of 4 m lanes, dt = 0.1 s (simulation and policy frequency
10 Hz), the EV driven by a continuous ``[acceleration, steering]`` action in [-1, 1] that maps linearly
onto actuator ranges wider than the planning bounds (so violations of the bounds are measurable).
**Actions outside [-1, 1] are clipped; a non-finite action, or one that is not real numbers (a string, a complex
number, a bool), raises ValueError** (:func:`bimp.envs.checks.checked_action`). Speeds never go negative.

Configuration: ``gym.make(id, config={...})`` sets the base configuration. Scenario parameters (``PARAMS`` of
each env, listed with units and accepted values in its docstring) given as a 2-sequence ``(lo, hi)`` are drawn
uniformly from ``self.np_random`` at every ``reset``; a number fixes them. ``reset(options={"config": {...}})``
overrides the configuration *for that episode only* (Gymnasium's convention; highway-env would keep it): the next
plain ``reset()`` is back on the ``gym.make`` config. Both are validated before anything is simulated, and every
error is a ``ValueError`` naming the key and the value: an unknown key; a value that is not a finite real number or
a ``(lo, hi)`` pair of them with ``lo <= hi`` (bools, strings, NaN, inf, other lengths are refused); a value outside
the parameter's interval (speeds in [0, 40] m/s, gaps >= one vehicle length + d_min = 6 m between centres so
the vehicles start clear of each other and of the distance constraint, and <= ``MAX_GAP`` = 1 km so every position
stays inside the observation space, ``brake_decel`` a magnitude > 0, ...);
and orders that must hold for the worst case of the ranges, not only for one draw (OV2 ahead of OV1, the
reference's ``ref_zero_step`` after ``ref_hold``). highway-env's own keys (rendering) pass through, checked as the
adapter checks them (:func:`bimp.envs.checks.check_highway_config`); ``policy_frequency`` must be 10 Hz (the planners
plan at dt = 0.1 s) and ``action`` is refused (the EV is driven by the env's own continuous action).

Collision: ``info["collision"]`` is true exactly when the EV's footprint touches or overlaps an OV's, i.e. when
``min(info["ov_distance"]) <= 0``, the exact signed distance between the two 5 m x 2 m rectangles
(:meth:`bimp.envs.scene.Scene.ov_gaps`). It is measured on the simulated state itself: highway-env's collision handling
(which predicts an intersection one step ahead, pushes both vehicles apart by an "impact" translation and then
brakes crashed vehicles to a stop) is switched off for all vehicles, so no contact moves anyone, OV-OV contacts
included. The env checks the gap after every simulation step and ends the step at the first overlapping state.
The EV and the OVs it touches are marked ``crashed`` only so that highway-env draws them so.

Rendering: ``metadata["render_fps"]`` is the policy frequency, one frame per step as gymnasium's ``RecordVideo``
captures them, so videos play in real time (highway-env would double it, in a dict shared by all instances).
It is set per instance at every reset; ``RecordVideo`` reads it once, when it wraps the env.

Observation (flat ``Box``, float32, see :mod:`bimp.envs.scene`): EV ``[x, y, heading, speed]``, the previous
physical input ``[a, delta]``, per OV ``[present, x, y, heading, speed, acceleration]``, and the reference
``[v_ref, dv_ref/dt, lateral offset of the reference lane]``.

``info`` per step: ``collision``, ``offroad`` (any body corner past a road edge), ``ov_distance`` (signed
footprint gap to each OV, see above), ``edge_distance`` (least corner distance to the edge), ``ttc`` (time to
collision with the nearest closing OV in the EV's lane), ``reference``, ``lateral_error``, ``speed_error``,
``input`` (the physical input applied), ``constraints`` (paper eq. 2-5 as values that are <= 0 when satisfied; the
input and rate ones are :func:`bimp.envs.scene.bound_constraints`, the very function the planners' barriers measure),
and for the closed-loop score (:func:`bimp.envs.scene.attribution_info`, ``docs/suite.md``) ``contact`` (None, or
the OV in contact in the EV's body frame with both speeds and the EV's lateral speed across the road) and
``speed_limit`` (the cruise speed, the EV's initial speed: the road has no limit of its own).

Reward (for RL): tracking of the reference speed measured *along the road* and of the reference lane,
in [0, 1] per step, minus small penalties for inputs and rate beyond the planning bounds; -20 and
termination on collision or leaving the road. Progress is measured along the road so weaving and
spinning earn nothing, and stopping earns nothing while the reference speed is positive.
"""

from __future__ import annotations

import numpy as np

from bimp.envs.paper_env import (  # the shared machinery, importable from here as before
    CRASH_PENALTY,
    LANE_WIDTH,
    LANES,
    MAX_GAP,
    MIN_CENTRE_GAP,
    N_OBSTACLES,
    REFERENCE_COLOUR,
    ROAD_HALF_WIDTH,
    BimpEnv,
    BimpObservation,
    GapAcceptance,
)
from bimp.envs.paper_params import Order, Param
from bimp.envs.paper_vehicles import EgoVehicle, ObstacleVehicle
from bimp.envs.road import RoadGeometry
from bimp.envs.scene import MAX_SPEED


class OvertakingEnv(BimpEnv):
    """Paper V-A: curved two-lane highway; the EV (right lane, ~25 m/s) closes on two slower OVs that hold
    speed and lane: OV1 ahead in the EV's lane, OV2 further ahead in the left lane.

    The reference comes from the paper's "higher-level decision-making module" (section II), a behaviour layer
    in the env (``reference: behaviour``, the default): gap acceptance in the spirit of MOBIL sets the reference
    lane and speed at every step from the traffic. It passes a slower OV ahead when the other lane is free over a
    safe window (a headway ahead plus what the EV closes during a pass, a headway behind), returns to the right
    lane once the passed OV is behind by a safe gap, and when no lane is safe keeps its lane and follows the
    slower OV at its speed; it only ever names a lane of the road. ``reference: keep-lane`` is the discovery
    variant: the right lane at the EV's initial speed, so passing needs the constraints to push the plan off the
    reference. ``info["ahead_of_ov1"]``: the EV is ahead of OV1 (``overtake_rate`` of an episode is its last
    value). ``gap``s are measured between vehicle centres along the road [m]; speeds in m/s; ``arc_angle_deg``
    > 0 turns right. Episode: 15 s (150 steps)."""

    PARAMS = {
        "ev_speed": Param((23.0, 27.0), "EV initial and reference speed, m/s", 0.0, MAX_SPEED),
        "ov1_gap": Param((25.0, 35.0), "centre gap of OV1 (EV's lane) ahead of the EV, m", MIN_CENTRE_GAP, MAX_GAP),
        "ov1_speed": Param((15.0, 17.0), "OV1 speed, m/s", 0.0, MAX_SPEED),
        "ov2_gap": Param((100.0, 130.0), "centre gap of OV2 (left lane) ahead of the EV, m", MIN_CENTRE_GAP, MAX_GAP),
        "ov2_speed": Param((18.0, 20.0), "OV2 speed, m/s", 0.0, MAX_SPEED),
        "radius": Param((180.0, 220.0), "arc radius of the centreline, m, beyond the road's half width",
                        ROAD_HALF_WIDTH, low_open=True),
        "arc_angle_deg": Param((50.0, 70.0), "arc angle, degrees, > 0 turns right; at most a quarter turn, "
                               "so the straight after the arc never runs back beside the road", -90.0, 90.0),
    }
    # OV2 outpaces OV1 so that a pass exists on every instance: with OV2 no faster, the EV in the passing lane is
    # held at OV2's pace and may never get past OV1 (tests/envs/test_feasibility.py; on tuning seeds 100-199 of the
    # old ranges, 15-18 and 17-20 m/s, the 4 instances neither planner passed had OV2 at most 0.1 m/s faster).
    ORDERS = (Order("ov1_gap", "ov2_gap", "OV2 starts further ahead than OV1, clear of it even in one lane",
                    by=MIN_CENTRE_GAP),
              Order("ov1_speed", "ov2_speed", "OV2, ahead in the passing lane, outpaces OV1", by=1.0))
    OPTIONS = {"reference": ("behaviour", "keep-lane")}
    OVERTAKE_METRIC = True

    BEHAVIOUR = GapAcceptance()

    def _scene_road(self) -> RoadGeometry:
        return RoadGeometry(straight_in=100.0, radius=self._draw("radius"),
                            arc_angle=np.deg2rad(self._draw("arc_angle_deg")), straight_out=300.0)

    def _populate(self) -> tuple[float, int]:
        ev_speed = self._draw("ev_speed")
        self._add_obstacle(1, self._draw("ov1_gap"), self._draw("ov1_speed"))
        self._add_obstacle(0, self._draw("ov2_gap"), self._draw("ov2_speed"))
        self.target_lane, self.reference_speed = 1, ev_speed
        return ev_speed, 1

    def _reset(self) -> None:
        super()._reset()
        self._behave()

    def _simulate(self, action=None) -> None:
        super()._simulate(action)
        self._behave()  # the reference the next observation publishes

    def reference(self) -> np.ndarray:
        """The behaviour layer's lane and speed (``reference: behaviour``), or the EV's own lane at the cruise
        speed (``keep-lane``, the discovery variant: passing is left to the planner)."""
        if self.config["reference"] == "keep-lane":
            return super().reference()
        return np.array([self.reference_speed, 0.0, self.scene.geometry.lane_offset(self.target_lane)])

    def _traffic(self) -> tuple[float, float, list[tuple[float, float, int]]]:
        """The EV's arc length and speed, and each OV's ``(s, speed, lane)`` (lane: the nearest centre)."""
        road = self.scene.geometry
        s_e, _ = road.to_frenet(self.vehicle.position)
        rows = []
        for ov in self.obstacles:
            s_o, l_o = road.to_frenet(ov.position)
            lane = int(np.argmin(np.abs(l_o - road.lane_offset(np.arange(road.lanes)))))
            rows.append((float(s_o), float(ov.speed), lane))
        return float(s_e), float(self.vehicle.speed), rows

    def _behave(self) -> None:
        """Gap acceptance in the spirit of MOBIL: sets ``target_lane`` (always a lane of the road) and
        ``reference_speed`` from the traffic."""
        s_e, v_e, ovs = self._traffic()
        b = self.BEHAVIOUR
        length, cruise = self.scene.vehicle_length + self.scene.bounds.d_min, self.cruise_speed

        def ahead(lane):
            rows = [(s - s_e, v) for s, v, k in ovs if k == lane and s > s_e]
            return min(rows, default=(np.inf, np.inf))

        def behind(lane):
            rows = [(s_e - s, v) for s, v, k in ovs if k == lane and s <= s_e]
            return min(rows, default=(np.inf, 0.0))

        def free(lane):
            gap_a, v_a = ahead(lane)
            gap_b, v_b = behind(lane)
            closing = max(v_e - v_a, 0.0) * b.pass_s if np.isfinite(v_a) else 0.0
            return (gap_a - length >= b.headway_s * v_e + closing
                    and gap_b - length >= b.headway_s * max(v_b - v_e, 0.0) + b.return_s * v_e)

        current, other = self.target_lane, 1 - self.target_lane
        gap, v_lead = ahead(current)
        slower_ahead = v_lead < cruise - 0.5 and gap < b.consider_s * max(v_e, 1.0)
        if current == 0 and free(1):  # keep right: return once the passed OV is behind and the lane is clear
            self.target_lane = 1
        elif slower_ahead and free(other) and gap - length > b.lane_change_s * (v_e - v_lead):
            self.target_lane = other
        gap, v_lead = ahead(self.target_lane)
        # No safe lane: follow the slower OV ahead at its speed.
        follow = v_lead < cruise and gap < b.consider_s * max(v_e, 1.0)
        self.reference_speed = float(v_lead) if follow else cruise


class OvertakingKeepLaneEnv(OvertakingEnv):
    """:class:`OvertakingEnv` with ``reference: keep-lane`` as its default (``bimp/OvertakingKeepLane-v0``): the
    reference holds the right lane at the EV's initial speed, so a pass must be discovered by the planner, pushed
    off the reference by the constraints (the paper's V-A setting; the claims study's exploration test)."""

    OPTIONS = {"reference": ("keep-lane", "behaviour")}


class EmergencyBrakeEnv(BimpEnv):
    """Paper V-B: straight two-lane road; an OV ahead in each lane brakes hard (``brake_decel`` m/s^2, a
    magnitude: the OVs accelerate by ``-brake_decel``) to a full stop from ``brake_onset`` s (sudden traffic
    build-up). The reference speed holds the cruise
    value (the EV's initial speed) for ``ref_hold`` s, then falls linearly to 0 at step ``ref_zero_step``.
    The EV must stop without collision and stay on the road. Episode: 12 s (120 steps)."""

    PARAMS = {
        "ev_speed": Param((23.0, 27.0), "EV initial (cruise) speed, m/s", 0.0, MAX_SPEED),
        # From 50 m: braking at the planning bounds (a_min, rate-limited) from the first observed deceleration
        # keeps >= d_min to OV1 on every instance of the ranges (worst corner 2.1 m; with 40 m it was -7.9 m:
        # tests/envs/test_feasibility.py).
        "ov1_gap": Param((50.0, 60.0), "centre gap of OV1 (EV's lane) ahead of the EV, m", MIN_CENTRE_GAP, MAX_GAP),
        "ov2_gap": Param((35.0, 55.0), "centre gap of OV2 (left lane) ahead of the EV, m", MIN_CENTRE_GAP, MAX_GAP),
        "ov_speed": Param((20.0, 24.0), "OV speed before braking (drawn per OV), m/s", 0.0, MAX_SPEED),
        "brake_onset": Param((0.8, 1.2), "time at which the OVs start braking, s", 0.0),
        "brake_decel": Param((5.0, 7.0), "a deceleration magnitude, m/s^2", 0.0, low_open=True),
        "ref_hold": Param(3.0, "time the reference speed holds the cruise speed, s", 0.0),
        "ref_zero_step": Param(80, "policy step at which the reference speed reaches 0", 1, integer=True),
    }
    ORDERS = (Order("ref_hold", "ref_zero_step", "the reference falls to 0 only after it stops holding",
                    strict=True, later_in_steps=True),)

    def _scene_road(self) -> RoadGeometry:
        return RoadGeometry(straight_in=100.0, arc_angle=0.0, straight_out=400.0)

    def _populate(self) -> tuple[float, int]:
        ev_speed = self._draw("ev_speed")
        onset, decel = self._draw("brake_onset"), self._draw("brake_decel")
        self._add_obstacle(1, self._draw("ov1_gap"), self._draw("ov_speed"), brake_onset=onset, decel=decel)
        self._add_obstacle(0, self._draw("ov2_gap"), self._draw("ov_speed"), brake_onset=onset, decel=decel)
        # ORDERS guarantees ref_zero > ref_hold for every draw.
        self.ref_hold, self.ref_zero = self._draw("ref_hold"), self._draw("ref_zero_step") * self.scene.dt
        return ev_speed, 1

    def reference(self) -> np.ndarray:
        ref = super().reference()
        slope = self.cruise_speed / (self.ref_zero - self.ref_hold)
        t = self.time
        if t < self.ref_hold:
            return ref
        if t >= self.ref_zero - 1e-9:
            return np.array([0.0, 0.0, ref[2]])
        return np.array([self.cruise_speed - slope * (t - self.ref_hold), -slope, ref[2]])


__all__ = ["CRASH_PENALTY", "LANES", "LANE_WIDTH", "MAX_GAP", "MAX_SPEED", "MIN_CENTRE_GAP", "N_OBSTACLES",
           "REFERENCE_COLOUR", "ROAD_HALF_WIDTH", "BimpEnv", "BimpObservation", "EgoVehicle", "EmergencyBrakeEnv",
           "GapAcceptance", "ObstacleVehicle", "Order", "OvertakingEnv", "OvertakingKeepLaneEnv", "Param"]
