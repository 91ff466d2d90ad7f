"""The loopback world: the paper's sandbox simulated on the CPU (see docs/world.md).

Pure modules (no ROS): ``scene``, ``raycast``, ``points``, ``virtual``, ``route``, ``kinematics``,
``recorder``, ``cli``. ROS nodes: ``camera_node`` (gsrmr-mock-camera), ``route_follower``.
"""

from gsrmr_server.world.points import make_world
from gsrmr_server.world.recorder import Round2Record, SlotRecord, record_round1, record_round2, with_resolution
from gsrmr_server.world.scene import Scene, SceneError, load_scene, parse_scene
from gsrmr_server.world.virtual import VirtualViewSource, compose_mask, mr_image

__all__ = ["Round2Record", "Scene", "SceneError", "SlotRecord", "VirtualViewSource", "compose_mask",
           "load_scene", "make_world", "mr_image", "parse_scene", "record_round1", "record_round2",
           "with_resolution"]
