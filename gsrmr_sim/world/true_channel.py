"""The simulated world's true uplink channel (pure: no ROS): one gain per slot, reproducible per seed.

The rule (fading from (``channel_seed``, round slot), path loss at the true position in ``map``, metres; slots
before the round carry ``round_slot = −1``): docs/world.md, "Nodes", ``gsrmr-sim-channel``.
"""

from __future__ import annotations

from gsrmr_common.link_model import LinkBudget
from gsrmr_common.pose2d import Pose2D
from gsrmr_common.wire import ChannelSample
from gsrmr_sim.world.kinematics import has_moved


class TrueChannel:
    """Per-slot channel gains of the simulated world (see the module docstring)."""

    def __init__(self, link: LinkBudget) -> None:
        self.link = link
        self.pose: Pose2D | None = None
        self.rest_pose: Pose2D | None = None
        self.round_start_slot: int | None = None

    def observe_pose(self, pose: Pose2D) -> None:
        """The robot's true pose now (map, m, rad); the first motion arms the round start."""
        self.pose = pose
        self.rest_pose = self.rest_pose or pose

    def moving(self) -> bool:
        """Whether the robot has left its rest pose."""
        return self.pose is not None and self.rest_pose is not None and has_moved(self.pose, self.rest_pose)

    def sample(self, slot: int) -> ChannelSample:
        """The gain of absolute slot ``slot`` at the current true position; starts the round clock at
        the first slot sampled after the robot moved."""
        if self.round_start_slot is None and self.moving():
            self.round_start_slot = int(slot)
        position = self.pose[:2] if self.pose is not None else None
        if self.round_start_slot is not None and slot >= self.round_start_slot:
            k = int(slot) - self.round_start_slot
            return ChannelSample(int(slot), k, self.link.gain(k, position))
        return ChannelSample(int(slot), -1, self.link.gain(int(slot), position))
