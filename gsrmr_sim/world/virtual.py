"""The MR content a scene is composited with, for the simulator's ground truth and recordings.

The virtual world is the server's (:mod:`gsrmr_server.mr`), which a scene names (``mr_content``); the simulator
occludes it with the *real* depth, which only the world knows (docs/world.md, "Virtual view v_t and mask d_t").
"""

from __future__ import annotations

from gsrmr_server.mr.content import AgentsView, load_mr_content
from gsrmr_sim.world.scene import Scene


def virtual_view(scene: Scene) -> AgentsView:
    """The built-in virtual view of the MR content ``scene.mr_content`` names."""
    return AgentsView(load_mr_content(scene.mr_content))
