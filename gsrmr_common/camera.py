"""Camera model and axis conventions: every camera that turns a robot pose into an image is built here.

The "real" camera of the simulated world, the GS renderer Φ(s_t) and the virtual view v_t all use it:

* world (``map``/``odom``, REP-103): x forward, y left, z up, metres; a robot pose ``(a, b, θ)`` is ``base_link``
  on the floor (z = 0), θ in radians counter-clockwise about +z, 0 facing world +x;
* camera mount on the robot: :class:`CameraMount`;
* optical frame (OpenCV / 3DGS / gsplat): x right, y down, z forward; ``world_to_camera`` is the 4×4 [R|t] taking
  world points into it, depth is camera-space z;
* pixel (u, v) covers [u, u+1) × [v, v+1), centre (u + 0.5, v + 0.5) (3DGS / gsplat / COLMAP): a camera point
  (x, y, z) lands at ``(fx·x/z + cx, fy·y/z + cy)``. ROS ``CameraInfo`` and OpenCV put centres at integers, so
  their principal point is 0.5 px smaller: :meth:`Intrinsics.from_ros_k`, :meth:`Intrinsics.ros_k`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
import math

import numpy as np

# Rotation that maps optical-frame vectors into base_link for an untilted camera:
# optical x (right) -> -y_base, optical y (down) -> -z_base, optical z (forward) -> +x_base.
_OPTICAL_TO_BASE = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels, principal point in the pixel-centre-at-0.5 convention."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            if not math.isfinite(value):
                raise ValueError(f"camera intrinsics: {name} must be finite, got {value}")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"camera intrinsics: focal lengths must be > 0, got fx={self.fx} fy={self.fy}")
        if int(self.width) != self.width or int(self.height) != self.height:
            raise ValueError("camera intrinsics: width and height must be integers")
        if self.width < 1 or self.height < 1:
            raise ValueError(f"camera intrinsics: image must be at least 1×1, got {self.width}×{self.height}")

    @classmethod
    def from_fov(cls, width: int, height: int, horizontal_fov_rad: float) -> Intrinsics:
        """Square pixels, principal point at the image centre, given the horizontal field of view."""
        if not 0.0 < horizontal_fov_rad < math.pi:
            raise ValueError(f"horizontal_fov_rad must be in (0, π), got {horizontal_fov_rad}")
        focal = 0.5 * width / math.tan(0.5 * horizontal_fov_rad)
        return cls(focal, focal, 0.5 * width, 0.5 * height, int(width), int(height))

    @classmethod
    def from_k(cls, k: np.ndarray, width: int, height: int) -> Intrinsics:
        """From a 3×3 K already in the pixel-centre-at-0.5 convention (3DGS, gsplat, COLMAP, nerfstudio)."""
        k = np.asarray(k, dtype=np.float64).reshape(3, 3)
        return cls(float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]), int(width), int(height))

    @classmethod
    def from_ros_k(cls, k: np.ndarray, width: int, height: int) -> Intrinsics:
        """From a ROS CameraInfo / OpenCV K (pixel centres at integers): shifts cx, cy by +0.5."""
        k = np.asarray(k, dtype=np.float64).reshape(3, 3)
        return cls(float(k[0, 0]), float(k[1, 1]), float(k[0, 2]) + 0.5, float(k[1, 2]) + 0.5,
                   int(width), int(height))

    def k(self) -> np.ndarray:
        """3×3 K in the pixel-centre-at-0.5 convention."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def ros_k(self) -> np.ndarray:
        """3×3 K for ROS CameraInfo / OpenCV (pixel centres at integers)."""
        k = self.k()
        k[0, 2] -= 0.5
        k[1, 2] -= 0.5
        return k

    def scaled(self, width: int, height: int) -> Intrinsics:
        """The same field of view at another resolution."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, int(width), int(height))


@dataclass(frozen=True)
class CameraMount:
    """Where the camera sits on the robot: the pose of the camera body frame (``camera_link``: x forward, y left,
    z up) in ``base_link`` — metres and radians, REP-103.

    Translation ``(forward_m, left_m, height_m)``; rotation by the ROS roll-pitch-yaw convention
    R = Rz(yaw)·Ry(pitch)·Rx(roll) about base_link's fixed axes: ``pitch_rad`` > 0 tips the optical axis down,
    ``yaw_rad`` > 0 turns it left, ``roll_rad`` > 0 tips the camera's right side down. The optical
    frame (x right, y down, z forward) sits at the same point, turned by the fixed ``camera_link`` →
    optical rotation. A real mount is measured (or read from the robot's static TF: :meth:`from_optical_pose`).
    """

    height_m: float = 0.15
    pitch_rad: float = 0.0
    forward_m: float = 0.1
    left_m: float = 0.0
    roll_rad: float = 0.0
    yaw_rad: float = 0.0

    def __post_init__(self) -> None:
        for name in ("height_m", "pitch_rad", "forward_m", "left_m", "roll_rad", "yaw_rad"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"camera mount: {name} must be finite")
        if abs(self.pitch_rad) >= 0.5 * math.pi:
            raise ValueError(f"camera mount: |pitch_rad| must be < π/2, got {self.pitch_rad}")
        for name in ("roll_rad", "yaw_rad"):
            if abs(getattr(self, name)) > math.pi:
                raise ValueError(f"camera mount: |{name}| must be ≤ π, got {getattr(self, name)}")

    def as_parameters(self, prefix: str = "camera_mount.") -> dict[str, float]:
        """The mount as the ``camera_mount.*`` node parameters (``config/camera_mount.yaml``) name it."""
        return {f"{prefix}{f.name}": float(getattr(self, f.name)) for f in fields(self)}

    def body_rotation(self) -> np.ndarray:
        """3×3 rotation of ``camera_link`` in ``base_link``: Rz(yaw)·Ry(pitch)·Rx(roll)."""
        return rpy_matrix(self.roll_rad, self.pitch_rad, self.yaw_rad)

    @classmethod
    def from_optical_pose(cls, base_from_optical: np.ndarray) -> CameraMount:
        """The mount of a camera whose optical frame has the 4×4 pose ``base_from_optical`` in ``base_link``
        (e.g. composed from a robot's static TF). Raises ``ValueError`` for a camera looking straight up or
        down (|pitch| ≥ π/2: roll and yaw are not separable there)."""
        m = np.asarray(base_from_optical, dtype=np.float64).reshape(4, 4)
        body = m[:3, :3] @ _OPTICAL_TO_BASE.T
        pitch = math.asin(max(-1.0, min(1.0, -body[2, 0])))
        if abs(abs(pitch) - 0.5 * math.pi) < 1e-6:
            raise ValueError("camera mount: the camera looks straight up or down (pitch ±π/2)")
        roll = math.atan2(body[2, 1], body[2, 2])
        yaw = math.atan2(body[1, 0], body[0, 0])
        x, y, z = (float(v) for v in m[:3, 3])
        return cls(height_m=z, pitch_rad=pitch, forward_m=x, left_m=y, roll_rad=roll, yaw_rad=yaw)


def rpy_matrix(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """3×3 rotation Rz(yaw)·Ry(pitch)·Rx(roll) (ROS/URDF roll-pitch-yaw about fixed axes; radians)."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return rz @ ry @ rx


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: intrinsics plus a world→camera rigid transform in OpenCV axes."""

    intrinsics: Intrinsics
    world_to_camera: np.ndarray = field(repr=False)

    def __post_init__(self) -> None:
        w2c = np.asarray(self.world_to_camera, dtype=np.float64)
        if w2c.shape != (4, 4) or not np.all(np.isfinite(w2c)):
            raise ValueError("world_to_camera must be a finite 4×4 matrix")
        rot = w2c[:3, :3]
        if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-5) or np.linalg.det(rot) < 0:
            raise ValueError("world_to_camera rotation must be orthonormal and right-handed")
        object.__setattr__(self, "world_to_camera", w2c)

    @property
    def width(self) -> int:
        return self.intrinsics.width

    @property
    def height(self) -> int:
        return self.intrinsics.height

    @property
    def camera_to_world(self) -> np.ndarray:
        """4×4 inverse of ``world_to_camera`` (columns of R: camera x/y/z axes in the world)."""
        rot = self.world_to_camera[:3, :3]
        out = np.eye(4)
        out[:3, :3] = rot.T
        out[:3, 3] = -rot.T @ self.world_to_camera[:3, 3]
        return out

    @property
    def center_world(self) -> np.ndarray:
        """Optical centre in world coordinates (metres)."""
        return self.camera_to_world[:3, 3]

    def to_camera(self, points_world: np.ndarray) -> np.ndarray:
        """N×3 world points → N×3 camera-frame points (x right, y down, z forward)."""
        pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        return pts @ self.world_to_camera[:3, :3].T + self.world_to_camera[:3, 3]

    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """N×3 world points → (N×2 pixel coordinates in the 0.5-centre convention, N depths z).

        Points with z ≤ 0 get NaN pixel coordinates.
        """
        cam = self.to_camera(points_world)
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack([self.intrinsics.fx * cam[:, 0] / z + self.intrinsics.cx,
                           self.intrinsics.fy * cam[:, 1] / z + self.intrinsics.cy], axis=1)
        uv[z <= 0] = np.nan
        return uv, z

    def ray_directions_camera(self) -> np.ndarray:
        """H×W×3 un-normalised ray directions (z = 1) through every pixel centre, camera frame."""
        k = self.intrinsics
        u = (np.arange(k.width) + 0.5 - k.cx) / k.fx
        v = (np.arange(k.height) + 0.5 - k.cy) / k.fy
        uu, vv = np.meshgrid(u, v)
        return np.stack([uu, vv, np.ones_like(uu)], axis=-1)

    def rays_world(self) -> tuple[np.ndarray, np.ndarray]:
        """(origin 3-vector, H×W×3 unit ray directions in the world) through every pixel centre."""
        dirs = self.ray_directions_camera() @ self.camera_to_world[:3, :3].T
        dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
        return self.center_world, dirs


def base_to_camera_rotation(mount: CameraMount) -> np.ndarray:
    """3×3 rotation taking optical-frame vectors into ``base_link`` for this mount (pitch down > 0)."""
    return mount.body_rotation() @ _OPTICAL_TO_BASE


def camera_to_world_from_pose(a_m: float, b_m: float, theta_rad: float, mount: CameraMount) -> np.ndarray:
    """4×4 camera→world transform of a camera on a robot at pose (a, b, θ)."""
    for name, value in (("a", a_m), ("b", b_m), ("theta", theta_rad)):
        if not math.isfinite(value):
            raise ValueError(f"robot pose: {name} must be finite, got {value}")
    c, s = math.cos(theta_rad), math.sin(theta_rad)
    yaw = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    out = np.eye(4)
    out[:3, :3] = yaw @ base_to_camera_rotation(mount)
    out[:3, 3] = np.array([a_m, b_m, 0.0]) + yaw @ np.array([mount.forward_m, mount.left_m, mount.height_m])
    return out


def camera_from_pose(a_m: float, b_m: float, theta_rad: float, mount: CameraMount,
                     intrinsics: Intrinsics) -> Camera:
    """The camera of a robot at pose (a, b, θ) with the given mount and intrinsics."""
    c2w = camera_to_world_from_pose(a_m, b_m, theta_rad, mount)
    w2c = np.eye(4)
    w2c[:3, :3] = c2w[:3, :3].T
    w2c[:3, 3] = -c2w[:3, :3].T @ c2w[:3, 3]
    return Camera(intrinsics, w2c)


def opengl_c2w_to_opencv_w2c(transform_matrix: np.ndarray) -> np.ndarray:
    """nerfstudio / Blender camera→world (x right, y up, z back) → OpenCV world→camera 4×4."""
    c2w = np.asarray(transform_matrix, dtype=np.float64).reshape(4, 4).copy()
    c2w[:3, 1:3] *= -1.0
    w2c = np.eye(4)
    w2c[:3, :3] = c2w[:3, :3].T
    w2c[:3, 3] = -c2w[:3, :3].T @ c2w[:3, 3]
    return w2c


def opencv_w2c_to_opengl_c2w(world_to_camera: np.ndarray) -> np.ndarray:
    """OpenCV world→camera 4×4 → nerfstudio / Blender camera→world (x right, y up, z back)."""
    w2c = np.asarray(world_to_camera, dtype=np.float64).reshape(4, 4)
    c2w = np.eye(4)
    c2w[:3, :3] = w2c[:3, :3].T
    c2w[:3, 3] = -w2c[:3, :3].T @ w2c[:3, 3]
    c2w[:3, 1:3] *= -1.0
    return c2w
