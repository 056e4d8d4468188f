"""The adapter's one table of per-id numbers (:data:`PROFILES`): highway-env's ids and the suite's families, each
with its planning bounds, actuator steering range, free-road target speed and duration."""

from __future__ import annotations

from dataclasses import dataclass

from bimp.configs import added_field
from bimp.envs.scene import ACTUATOR_STEER, Bounds
from bimp.envs.suite import FAMILIES


@dataclass(frozen=True)
class Profile:
    """What the adapter needs per id: the planning ``bounds``, the ``actuator_steer`` range [rad] that the
    normalized steering maps onto (the acceleration maps onto bimp's ±10 m/s^2 everywhere), the free-road
    ``target_speed`` [m/s] of the behaviour layer (from the env's config: the top of its reward speed range or of
    its discrete action's target speeds), ``duration`` [s] (highway-env's, for the registration's step limit), and
    ``drive_on``: whether the behaviour layer drives on where the route's next road leaves from another lane (exit-v0,
    the exit missed: :class:`bimp.envs.highway.behaviour.DriveOnDriver`); ``overtake``: whether it overtakes through
    the lane of oncoming traffic (the suite's two-way-overtake: :class:`bimp.envs.highway.behaviour.OvertakeDriver`);
    ``junction``: a road whose junctions the EV crosses (roundabout-v0, intersection-v0): the behaviour layer yields
    there by gap acceptance (:mod:`bimp.envs.highway.junction`), and the reference's lane is the EV's own road's until
    it is on the next one (highway-env's driver turns to the next lane a little before the road's end: at
    roundabout-v0's entry, the ring lane abreast lies 2.3 m beside the entry); ``lateral_accel`` [m/s^2]: where
    finite, the reference's acceleration also keeps the EV at or below each curve's speed ahead for that lateral
    acceleration (:func:`bimp.envs.highway.behaviour.curve_acceleration`; highway-env's IDM takes a curve at its
    target speed, steering up to 60 degrees at once, and the planners' bounded steering does not); ``gap_plan``: the
    behaviour layer plans its way through the gaps into the lane its route needs (exit-v0's exit lane, which MOBIL
    never heads for: :class:`bimp.envs.highway.behaviour.GapDriver`); ``lane_path``: the reference's lane is where
    that plan holds the EV 2 s ahead (``GapDriver.lead_point``), and the planners track its path's heading
    (``Scene.lane_path``)."""

    bounds: Bounds
    actuator_steer: tuple[float, float]
    target_speed: float
    duration: float
    drive_on: bool = added_field(False, neutral=False)
    overtake: bool = added_field(False, neutral=False)
    junction: bool = added_field(False, neutral=False)
    lateral_accel: float = added_field(float("inf"), neutral=float("inf"))
    gap_plan: bool = added_field(False, neutral=False)
    lane_path: bool = added_field(False, neutral=False)

    def __post_init__(self) -> None:
        if self.lane_path and not self.gap_plan:
            raise ValueError("a profile's lane_path leads along the gap plan: it needs gap_plan")


def _curve_bounds(steer: float) -> Bounds:
    # The paper's bounds with a steering bound that takes the road's tightest curve, and a steering rate that
    # reaches it in 1 s (10 steps): highway-env's bicycle needs tan(delta) = 2 tan(asin(L / (2 R))), L = 5 m.
    return Bounds(steer=steer, steer_rate=steer / 10.0)


# m/s^2: the junction roads' curve speed, about 0.4 g (the ring at 9.8 m/s, the roundabout's entry and the
# intersection's right turn, radius 9 m, at 6 m/s)
CURVE_ACCEL = 4.0
_STRAIGHT = Bounds()  # the paper's: straight roads and lane changes need no more than 0.05 rad
# The one table of per-id numbers. Tightest radius on the EV's route -> steering needed -> planning bound (about 20%
# above it) -> actuator range (wider still, so violations of the bound stay measurable).
PROFILES: dict[str, Profile] = {
    # straight multi-lane roads; target: the top of reward_speed_range (30 m/s)
    "highway-v0": Profile(_STRAIGHT, ACTUATOR_STEER, 30.0, 40.0),
    "highway-fast-v0": Profile(_STRAIGHT, ACTUATOR_STEER, 30.0, 30.0),
    "merge-v0": Profile(_STRAIGHT, ACTUATOR_STEER, 30.0, 40.0),  # no duration of its own: highway-env's goal x > 370
    # the exit lane leaves straight; target: the top of its target_speeds (30 m/s)
    "exit-v0": Profile(_STRAIGHT, ACTUATOR_STEER, 30.0, 18.0, drive_on=True, gap_plan=True,
                       lane_path=True),
    # the entry's turn into the ring, the route's blend across the gap (lanes.smooth_bridges): radius 8 m over 5 m,
    # 0.58 rad needed, a thin 3% under the bound (the ring itself, radius 20 m on the inner lane: 0.247 rad)
    "roundabout-v0": Profile(_curve_bounds(0.6), (-0.8, 0.8), 16.0, 20.0, junction=True, lateral_accel=CURVE_ACCEL),
    # straight; overtaking in the oncoming lane; MDPVehicle's top target speed
    "two-way-v0": Profile(_STRAIGHT, ACTUATOR_STEER, 30.0, 40.0),
    # a half turn of radius 20 m (inner lane): 0.247 rad; the lanes' 20 m/s limit (highway-env's default) caps IDM
    "u-turn-v0": Profile(_curve_bounds(0.3), (-0.5, 0.5), 24.0, 10.0),
    # tightest turn radius 15 m: 0.326 rad; speed limit 10 m/s
    "racetrack-v0": Profile(_curve_bounds(0.4), (-0.6, 0.6), 10.0, 30.0),
    # right turn of radius 9 m: 0.524 rad; target: the top of its target_speeds (9 m/s)
    "intersection-v0": Profile(_curve_bounds(0.6), (-0.8, 0.8), 9.0, 20.0, junction=True, lateral_accel=CURVE_ACCEL),
}
SUPPORTED = tuple(PROFILES)  # highway-env's ids, what wrap(gym.make(ID)) takes
# racetrack-v0's duration (300 s) is shortened to 30 s for bimp. roundabout-v0's (11 s) and intersection-v0's (13 s)
# are lengthened to 20 s: an EV that yields at the entry or the crossing for a few seconds runs out of highway-env's
# time before its exit (roundabout-v0's route takes about 9 s without waiting). A config's own duration is kept.

# The suite's families in the same table, keyed by their ID (registered as bimp/ID): each family class carries its
# numbers, so a new family adds no line here (bimp.envs.suite.family.Family).
PROFILES.update({cls.ID: Profile(cls.BOUNDS, cls.ACTUATOR_STEER, cls.TARGET_SPEED, cls.DURATION,
                                 overtake=cls.OVERTAKE) for cls in FAMILIES.values()})
