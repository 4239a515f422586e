"""Geometry of the simulated scanner: pinhole camera, turntable axis, laser and board.

Conventions follow ``docs/capture-format.md`` (world frame in the laser plane,
``x`` right as the camera sees it, ``y`` away from the camera, ``z`` up, mm) and
``lamina_shared.types`` (pixel ``(i, j)`` centre at exactly ``u = i, v = j``).
The layout mirrors the thesis prototype (section 3.2.1): camera inclined 30 degrees,
object about 10 cm away.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from lamina_shared.presets import RIG_PRESETS, make_preset
from lamina_shared.types import BoardSpec, LiftReference

__all__ = ["RIG_PRESETS", "Rig"]


@dataclass(frozen=True)
class Rig:
    """The true (simulated) scanner geometry; calibration must recover what it can of it."""

    image_size: tuple[int, int] = (640, 480)
    # 640 px * 100 mm / 1422 px ~= 45 mm across the image at the axis distance.
    focal_px: float = 1422.0
    camera_distance_mm: float = 100.0
    tilt_deg: float = 30.0
    axis_xy_mm: tuple[float, float] = (0.6, -0.4)
    # Beside and in front of the axis, so the camera and laser shadow different arcs.
    laser_source_xy_mm: tuple[float, float] = (15.0, -85.0)
    # ~0.16 mm gives a stripe of ~2 px sigma on a wall facing the camera near the axis.
    laser_sigma_mm: float = 0.16
    # 143 corners of 2 mm: error falls with the corner count (thesis fig. 4.7), and this
    # many bring the 2.25 px^2 calibration study under 0.05 mm (tests/benchmarks).
    board: BoardSpec = BoardSpec((13, 11), 2.0, (-12.0, -10.0))  # noqa: RUF009 (frozen)
    cylinder_diameter_mm: float = 19.05
    cylinder_offset_mm: tuple[float, float] = (1.5, -0.8)
    cylinder_height_mm: float = 40.0
    """The calibration cylinder stands on its base 5 mm below the first section."""
    cylinder_grooves_mm: tuple[float, ...] = ()
    """Heights of the centres of the cylinder's two V-grooves, the lift's length standard
    (:class:`~lamina_shared.types.LiftReference`); none: the lift is trusted."""
    groove_depth_mm: float = 5.0
    # Radial lens distortion, the division model the host calibration fits (Fitzgibbon):
    # a pixel at distorted offset d from the image centre sees the undistorted pinhole
    # pixel centre + d / (1 + k (|d| / R)^2), R the half diagonal. 0 is a pinhole; k < 0
    # is barrel distortion, as on the Pi camera's stock lenses.
    division_k: float = 0.0

    @classmethod
    def limb(cls) -> Rig:
        """Return a limb-scale rig: objects up to ~150 mm across, 1536x864 camera.

        Camera Module 3 binned mode (1536x864, ~1700 px focal length with the stock lens)
        300 mm from the axis, 30 degrees above the sheet: ~270 mm across the image at the
        axis. The laser fan, board and cylinder grow with it (a 60 mm pipe as cylinder).
        """
        return cls(
            image_size=(1536, 864),
            focal_px=1700.0,
            camera_distance_mm=300.0,
            axis_xy_mm=(2.0, -1.5),
            laser_source_xy_mm=(60.0, -340.0),
            laser_sigma_mm=0.5,
            board=BoardSpec((13, 9), 12.0, (-72.0, -48.0)),
            cylinder_diameter_mm=60.0,
            cylinder_offset_mm=(10.0, -6.0),
            # A 185 mm pipe with two grooves 140 mm apart: the lift's length standard.
            cylinder_height_mm=185.0,
            cylinder_grooves_mm=(25.0, 165.0),
        )

    def lift_reference(self) -> LiftReference | None:
        """Return the lift reference the cylinder's grooves give (None without grooves).

        The lift sections meet the middle of each groove's lower flank, half its depth
        below the groove's centre (a 90 degree V: the flank is as tall as it is deep).
        """
        if len(self.cylinder_grooves_mm) != 2:
            return None
        low, high = sorted(self.cylinder_grooves_mm)
        half = self.groove_depth_mm / 2.0
        return LiftReference((low - half, high - half), high - low, 1.0, self.groove_depth_mm)

    @classmethod
    def preset(cls, name: str) -> Rig:
        """Return the rig named ``name`` (one of ``RIG_PRESETS``)."""
        makers: dict[str, Callable[[], Rig]] = {"thesis": cls, "limb": cls.limb}
        return make_preset("rig", name, makers)

    @property
    def principal_point_px(self) -> tuple[float, float]:
        """Return ``(cx, cy)``, the image centre in the pixel-centre convention."""
        w, h = self.image_size
        return ((w - 1) / 2.0, (h - 1) / 2.0)

    @property
    def camera_matrix(self) -> np.ndarray:
        """Return the 3x3 intrinsic matrix K."""
        cx, cy = self.principal_point_px
        return np.array([[self.focal_px, 0.0, cx], [0.0, self.focal_px, cy], [0.0, 0.0, 1.0]])

    @property
    def distortion_radius_px(self) -> float:
        """Return R, the radius that normalises ``division_k``: the image's half diagonal."""
        w, h = self.image_size
        return math.hypot(w - 1, h - 1) / 2.0

    def _from_centre(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return the principal point, ``uv``'s offsets from it and their squared radius
        in units of the distortion radius."""
        c = np.asarray(self.principal_point_px)
        d = uv - c
        return c, d, np.sum(d * d, axis=-1, keepdims=True) / self.distortion_radius_px**2

    def undistort_px(self, uv: np.ndarray) -> np.ndarray:
        """Map observed (distorted) pixel coordinates (..., 2) to ideal pinhole ones."""
        uv = np.asarray(uv, dtype=float)
        if self.division_k == 0.0:
            return uv
        c, d, r2 = self._from_centre(uv)
        return c + d / (1.0 + self.division_k * r2)

    def distort_px(self, uv: np.ndarray) -> np.ndarray:
        """Map ideal pinhole pixel coordinates (..., 2) to where the lens images them."""
        uv = np.asarray(uv, dtype=float)
        if self.division_k == 0.0:
            return uv
        c, d, ru2 = self._from_centre(uv)
        # r_u = r_d / (1 + k r_d^2) solved for the root that tends to r_u as k -> 0.
        return c + d * (2.0 / (1.0 + np.sqrt(np.maximum(1.0 - 4.0 * self.division_k * ru2, 0.0))))

    @property
    def camera_centre_mm(self) -> np.ndarray:
        """Return the camera centre in world coordinates (above the plane, on the -y side)."""
        t = math.radians(self.tilt_deg)
        ax, ay = self.axis_xy_mm
        d = self.camera_distance_mm
        return np.array([ax, ay - d * math.cos(t), d * math.sin(t)])

    @property
    def rotation(self) -> np.ndarray:
        """Return R whose rows are the camera x (right), y (down) and z (forward) axes in world."""
        t = math.radians(self.tilt_deg)
        forward = np.array([0.0, math.cos(t), -math.sin(t)])
        right = np.array([1.0, 0.0, 0.0])
        down = np.cross(forward, right)  # OpenCV camera frame is right-handed: x * y = z
        return np.stack([right, down, forward])

    @property
    def laser_source_mm(self) -> np.ndarray:
        """Return the laser fan origin as a 3D world point (it lies in the plane z = 0)."""
        return np.array([*self.laser_source_xy_mm, 0.0])

    def plane_homography(self) -> np.ndarray:
        """Return H mapping plane points ``(x, y, 1)`` (z = 0) to ideal pinhole ``(u, v, 1)``."""
        r = self.rotation
        t = -r @ self.camera_centre_mm
        return self.camera_matrix @ np.column_stack([r[:, 0], r[:, 1], t])

    def project(self, xyz_world: np.ndarray) -> np.ndarray:
        """Project (N, 3) world points in mm to (N, 2) pixel coordinates ``(u, v)``."""
        p = np.asarray(xyz_world, dtype=float)
        cam = (p - self.camera_centre_mm) @ self.rotation.T
        cx, cy = self.principal_point_px
        u = cx + self.focal_px * cam[..., 0] / cam[..., 2]
        v = cy + self.focal_px * cam[..., 1] / cam[..., 2]
        return self.distort_px(np.stack([u, v], axis=-1))

    def backproject_to_plane(self, uv: np.ndarray) -> np.ndarray:
        """Return the (N, 2) world ``(x, y)`` where pixel rays through ``uv`` meet z = 0."""
        uv = self.undistort_px(uv)
        hom = np.concatenate([uv, np.ones((*uv.shape[:-1], 1))], axis=-1)
        xyw = hom @ np.linalg.inv(self.plane_homography()).T
        return xyw[..., :2] / xyw[..., 2:3]

    def object_to_world(self, q_obj_mm: np.ndarray, angle_deg: float, z_mm: float) -> np.ndarray:
        """Map object-frame points (N, 2) or (N, 3) to world (N, 3) for one view's angle and z."""
        q = np.asarray(q_obj_mm, dtype=float)
        qz = q[..., 2] if q.shape[-1] == 3 else np.zeros(q.shape[:-1])
        th = math.radians(angle_deg)
        c, s = math.cos(th), math.sin(th)
        x = self.axis_xy_mm[0] + c * q[..., 0] - s * q[..., 1]
        y = self.axis_xy_mm[1] + s * q[..., 0] + c * q[..., 1]
        return np.stack([x, y, qz - z_mm], axis=-1)

    def pixel_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Return the camera centre (3,) and unit ray directions (H, W, 3) through pixel centres."""
        w, h = self.image_size
        cx, cy = self.principal_point_px
        vv, uu = np.mgrid[0:h, 0:w].astype(float)
        if self.division_k != 0.0:
            ideal = self.undistort_px(np.stack([uu, vv], axis=-1))
            uu, vv = ideal[..., 0], ideal[..., 1]
        cam = np.stack([(uu - cx) / self.focal_px, (vv - cy) / self.focal_px, np.ones_like(uu)], -1)
        dirs = cam @ self.rotation  # camera -> world is R^T, applied to row vectors
        dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
        return self.camera_centre_mm.copy(), dirs
