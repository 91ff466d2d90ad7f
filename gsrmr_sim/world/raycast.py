"""The "real" camera of a box/cylinder scene: the room and its objects in one round, ray cast by
:mod:`gsrmr_shapes.raycast` (conventions, shading and timings are documented there)."""

from __future__ import annotations

import numpy as np

from gsrmr_common.camera import Camera
from gsrmr_shapes.raycast import MaterialTable, render_shapes
from gsrmr_sim.world.scene import Scene, WorldState


class RayCastWorld:
    """The real world of a box/cylinder scene in one round; ``render(camera, t_s)`` → (rgb, depth).

    ``round_index`` 1 ignores the scene's events; 2 applies them by round time ``t_s``.
    """

    def __init__(self, scene: Scene, round_index: int = 1) -> None:
        self.scene = scene
        self.round_index = int(round_index)

    def state(self, t_s: float) -> WorldState:
        """The real world's state at round time ``t_s``."""
        return self.scene.state_at(self.round_index, t_s)

    def render(self, camera: Camera, t_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Colour (H×W×3 float32 in [0, 1]) and depth (H×W float32, camera z in metres, +inf = nothing)."""
        state = self.state(t_s)
        mats = MaterialTable()
        room = None
        if self.scene.room is not None:
            r = self.scene.room
            room = np.array([*r.min_m, *r.max_m, mats.add(r.floor), mats.add(r.walls), mats.add(r.ceiling)],
                            dtype=np.float64)
        return render_shapes(camera, state.objects, state, room, mats, self.scene.background)
