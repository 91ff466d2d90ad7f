"""The loopback world: the paper's sandbox simulated on the CPU (docs/world.md, its module table).

Every module is pure (no ROS) but the nodes ``camera_node``, ``channel_node``, ``route_follower`` and ``scorer_node``.
The virtual agents are the server's MR content (:mod:`gsrmr_server.mr`).
"""

from gsrmr_sim.world.points import make_world
from gsrmr_sim.world.recorder import Round2Record, SlotRecord, record_round1, record_round2, with_resolution
from gsrmr_sim.world.scene import Scene, SceneError, load_scene, parse_scene
from gsrmr_sim.world.virtual import virtual_view

__all__ = ["Round2Record", "Scene", "SceneError", "SlotRecord", "load_scene", "make_world", "parse_scene",
           "record_round1", "record_round2", "virtual_view", "with_resolution"]
