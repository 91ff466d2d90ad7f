"""The MR content a scene is composited with, for the simulator's ground truth and recordings.

The virtual world is the server's (:mod:`gsrmr_server.mr`); a scene only names it (``mr_content``). The
simulator renders it with the *real* depth for occlusion, which only the world knows.
"""

from __future__ import annotations

from gsrmr_server.mr.content import AgentsView, load_mr_content
from gsrmr_sim.world.scene import Scene


def virtual_view(scene: Scene) -> AgentsView:
    """The built-in virtual view of the MR content ``scene.mr_content`` names."""
    return AgentsView(load_mr_content(scene.mr_content))
