"""Polylines in world coordinates drawn into a highway-env frame, under the traffic: how a frame shows what an agent
plans without the env knowing the agent (envs import neither planners nor agents).

A caller (``bimp.agents.rollout``: videos, ``bimp render``) sets ``env.unwrapped.overlay`` to a list of
``(points (n, 2) world [x, y] m, (r, g, b), width px)`` before the frame is rendered; the env's ``render``
(the paper's scenarios, :class:`bimp.envs.highway.adapter.HighwayAdapter`) hands it, after its own lines (the
scenarios' reference lane), to :func:`draw_lines`. Only in ``rgb_array`` mode: a ``human`` window has already
been drawn when highway-env's ``render`` returns.

highway-env's own hook for this, ``EnvViewer.set_agent_action_sequence``, is not used: it re-simulates a sequence
of *actions* with highway-env's vehicle (``Vehicle.predict_trajectory``) and draws the states as ghost vehicles, so
it cannot show the planner's own predicted states (its model may be the learned one) nor its particles; nor is
``EnvViewer.agent_display``, a class attribute (one callback for every viewer in the process) that also widens the
window with an agent panel. Drawing on the viewer's ``sim_surface`` after highway-env's frame, then the traffic
again on top, is what the scenarios already did for the reference lane.
"""

from __future__ import annotations

from typing import Iterable, Sequence

import numpy as np

Line = tuple[np.ndarray, Sequence[int], int]  # (points (n, 2) world m, (r, g, b), width px)


def draw_lines(env, lines: Iterable[Line] = ()) -> np.ndarray | None:
    """``lines`` and then ``env.overlay`` (if set) drawn on the viewer of ``env`` (a highway-env env whose
    ``render`` has just drawn its frame), the traffic redrawn on top; the new frame (``rgb_array``). None when there is
    nothing to draw or no viewer in ``rgb_array`` mode: the frame highway-env returned stands."""
    lines = [*lines, *(getattr(env, "overlay", None) or ())]
    if not lines or env.render_mode != "rgb_array" or env.viewer is None:
        return None
    import pygame  # highway-env's renderer, loaded by the render that came before
    from highway_env.road.graphics import RoadGraphics

    surface = env.viewer.sim_surface
    for points, colour, width in lines:
        points = np.asarray(points, dtype=float).reshape(-1, 2)
        points = points[np.all(np.isfinite(points), axis=1)]
        if len(points) >= 2:
            pygame.draw.lines(surface, tuple(colour), False, [surface.vec2pix(p) for p in points], int(width))
    RoadGraphics.display_road_objects(env.road, surface, offscreen=env.viewer.offscreen)
    RoadGraphics.display_traffic(env.road, surface, simulation_frequency=env.config["simulation_frequency"],
                                 offscreen=env.viewer.offscreen)
    return env.viewer.get_image()


__all__ = ["Line", "draw_lines"]
