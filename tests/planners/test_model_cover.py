"""Every road's planners plan on a model that covers the road's steering bound: "mlp" is the shipped model whose
envelope covers it (the paper's ±0.3 rad, or the wide ±0.8 rad one on the racetrack and the intersection), and a
model that does not cover the road's bound is refused naming both."""

import gymnasium as gym
import numpy as np
import pytest

from bimp import envs  # noqa: F401  (registers the envs)
from bimp.agents import make_policy
from bimp.envs.highway.profiles import PROFILES
from bimp.planners.dynamics import SHIPPED_WEIGHTS, BicycleModel, load_model, model_from_name, weights_for

NARROW, WIDE = SHIPPED_WEIGHTS


def test_the_shipped_models_envelopes():
    assert load_model(NARROW).steer_range == (-0.3, 0.3) and load_model(WIDE).steer_range == (-0.8, 0.8)


@pytest.mark.parametrize("env_id", sorted(PROFILES))
def test_every_roads_default_model_covers_its_planning_bound_and_the_paper_model_stays_where_it_does(env_id):
    bound = PROFILES[env_id].bounds.steer
    path = weights_for("mlp", bound)
    assert -load_model(path).steer_range[0] >= bound and load_model(path).steer_range[1] >= bound
    assert path == (NARROW if bound <= 0.3 else WIDE)  # the paper's model wherever it covers the road


def test_a_bound_no_model_covers_and_a_named_model_that_does_not_cover_are_refused_naming_both():
    with pytest.raises(ValueError, match=r"steering bound of 0\.9 rad \(the widest covers 0\.8\)"):
        weights_for("mlp", 0.9)
    with pytest.raises(ValueError, match=r"mlp\.pt covers steering up to 0\.3 rad, but this road's planning bound is "
                                         r"0\.6 rad"):
        weights_for(str(NARROW), 0.6)
    assert weights_for(str(WIDE), 0.6) == WIDE and weights_for("bicycle", 0.6) is None


@pytest.mark.parametrize("policy", ["enkts", "mppi"])
def test_planners_on_the_intersection_plan_on_the_wide_model_and_refuse_the_narrow_one(policy):
    env = gym.make("bimp/intersection-v0")
    planner = make_policy(policy, env)
    assert planner.artifacts == {"problem.dynamics": "bimp:planners/weights/mlp-wide.pt"}
    assert make_policy(policy, gym.make("bimp/highway-v0")).artifacts == {
        "problem.dynamics": "bimp:planners/weights/mlp.pt"}
    with pytest.raises(ValueError, match="covers steering up to 0.3 rad, but this road's planning bound is 0.6"):
        make_policy(policy, env, **{"problem.dynamics": str(NARROW)})


def test_the_wide_model_predicts_the_env_vehicle_in_a_tight_turn():
    # the intersection's right turn: 0.52 rad at 9 m/s, where the paper's model would clip at 0.3
    wide, exact = load_model(WIDE), BicycleModel(steer_range=(-0.8, 0.8))
    x_wide = x = np.tile([0.0, 0.0, 0.3, 9.0], (5, 1))
    u = np.column_stack([np.linspace(-3, 2, 5), np.full(5, 0.52)])
    for _ in range(20):  # 2 s open loop
        x_wide, x = wide.predict(x_wide, u), exact.predict(x, u)
    assert np.abs(x_wide[:, :2] - x[:, :2]).max() < 0.2 and np.abs(x_wide[:, 2] - x[:, 2]).max() < 0.02
    clipped = load_model(NARROW).predict(np.tile([0.0, 0.0, 0.3, 9.0], (5, 1)), u)
    assert np.abs(clipped[:, 2] - exact.predict(np.tile([0.0, 0.0, 0.3, 9.0], (5, 1)), u)[:, 2]).min() > 1e-2


def test_the_exact_bicycle_reaches_the_roads_bound():
    assert model_from_name("bicycle", 0.6).steer_range == (-0.6, 0.6)
    assert model_from_name("bicycle", 0.05).steer_range == BicycleModel().steer_range
