"""The plan in a frame (issue 26 item 7): videos and ``bimp render`` draw the planner's mean plan and a few particles,
on the paper's envs (with the reference lane) and on the wrapped highway-env envs; a policy without a plan draws
none. EnKTS runs with a small ensemble here: the frames, not the plans, are under test."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from bimp.agents.cli import main
from bimp.agents.registry import make_policy
from bimp.agents.rollout import PARTICLE_COLOUR, PLAN_COLOUR, plan_overlay, rollout, with_video
from bimp.envs.scenarios import REFERENCE_COLOUR

SMALL = {"n_particles": 16}
STEPS = 8


def _pixels(frame: np.ndarray, colour) -> int:
    return int(np.all(frame == colour, axis=-1).sum())


@pytest.fixture(scope="module")
def frames() -> dict[tuple[str, str], np.ndarray]:
    """``{(env id, policy): the frame after STEPS steps}``."""
    out = {}
    runs = (("bimp/Overtaking-v0", ("enkts", "lane-keep")), ("bimp/highway-fast-v0", ("enkts", "idm")))
    for env_id, policies in runs:
        for policy in policies:
            env = gym.make(env_id, render_mode="rgb_array")
            rollout(env, make_policy(policy, env, **(SMALL if policy == "enkts" else {})), 0, max_steps=STEPS)
            out[env_id, policy] = env.render()
            env.close()
    return out


@pytest.mark.parametrize("env_id", ["bimp/Overtaking-v0", "bimp/highway-fast-v0"])
def test_the_frame_draws_enkts_plan(frames, env_id):
    frame = frames[env_id, "enkts"]
    assert _pixels(frame, PLAN_COLOUR) > 150  # 3 px wide, tens of metres ahead at 4-5 px/m


@pytest.mark.parametrize("env_id, policy", [("bimp/Overtaking-v0", "lane-keep"), ("bimp/highway-fast-v0", "idm")])
def test_no_plan_no_plan_colour(frames, env_id, policy):
    frame = frames[env_id, policy]
    assert _pixels(frame, PLAN_COLOUR) == 0 and _pixels(frame, PARTICLE_COLOUR) == 0


@pytest.mark.parametrize("policy", ["enkts", "lane-keep"])
def test_the_paper_env_still_draws_the_reference_lane(frames, policy):
    assert _pixels(frames["bimp/Overtaking-v0", policy], REFERENCE_COLOUR) > 100


def test_the_overlay_holds_the_mean_and_particles_rolled_out_with_the_model():
    env = gym.make("bimp/Overtaking-v0")
    policy = make_policy("enkts", env, **SMALL)
    assert plan_overlay(policy) == []  # before the first act
    rollout(env, policy, 0, max_steps=3)
    lines = plan_overlay(policy, particles=4)
    assert [colour for _, colour, _ in lines] == [PARTICLE_COLOUR] * 4 + [PLAN_COLOUR]
    plan = policy.plan
    np.testing.assert_allclose(lines[-1][0], plan.states[:, :2])
    horizon = plan.controls.shape[0]
    for points, _, _ in lines[:-1]:  # from the plan's first state, within a few metres of the mean
        assert points.shape == (horizon + 1, 2)
        np.testing.assert_allclose(points[0], plan.states[0, :2], atol=1e-4)
        assert np.max(np.linalg.norm(points - plan.states[:, :2], axis=1)) < 5.0


def test_an_env_draws_the_lines_it_is_given_and_keeps_highway_envs_frame():
    """The env-side hook alone: ``env.unwrapped.overlay`` drawn on a wrapped highway-env env; without it, the frame
    is highway-env's own."""
    env = gym.make("bimp/highway-fast-v0", render_mode="rgb_array")
    env.reset(seed=0)
    plain = env.render()
    assert plain.shape == (150, 600, 3) and _pixels(plain, PLAN_COLOUR) == 0
    np.testing.assert_array_equal(plain, env.unwrapped.render())  # highway-env's own render, untouched
    ev = np.asarray(env.unwrapped.vehicle.position, float)
    env.unwrapped.overlay = [(ev + np.array([[0.0, 0.0], [40.0, 0.0]]), PLAN_COLOUR, 3)]
    assert _pixels(env.render(), PLAN_COLOUR) > 100
    env.close()


def test_the_video_frames_draw_the_plan(tmp_path):
    """The frames RecordVideo writes (MP4: colours approximate): none at the reset, the plan after the steps."""
    import imageio_ffmpeg

    env = with_video(gym.make("bimp/Overtaking-v0", render_mode="rgb_array"), tmp_path, "plan")
    rollout(env, make_policy("enkts", env, **SMALL), 0, max_steps=4)
    env.close()
    (video,) = tmp_path.glob("*.mp4")
    frames = imageio_ffmpeg.read_frames(str(video))
    meta = next(frames)
    shape = meta["size"][1], meta["size"][0], 3
    magenta = [int(np.sum((f[..., 0] > 200) & (f[..., 1] < 90) & (f[..., 2] > 200)))
               for f in (np.frombuffer(b, np.uint8).reshape(shape) for b in frames)]
    assert len(magenta) == 5 and magenta[0] < 20 and min(magenta[1:]) > 100, magenta


def test_bimp_render_writes_the_frame_as_png(tmp_path, capsys):
    assert main(["render", "--scenario", "overtaking", "highway-fast-v0", "--policy", "lane-keep", "--frame", "2",
                 "--out", str(tmp_path)]) == 0
    paths = capsys.readouterr().out.split()
    assert [p.rsplit("/", 1)[1] for p in paths] == ["Overtaking-v0.png", "highway-fast-v0.png"]
    import matplotlib.image

    assert matplotlib.image.imread(paths[1]).shape[:2] == (150, 600)
    assert main(["render", "--policy", "lane-keep", "--frame", "0", "--out", str(tmp_path)]) == 2
