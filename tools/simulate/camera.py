"""Pinhole camera on a pole or overpass: projection of road-frame 3D points and the road homography."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np


@dataclass(frozen=True)
class Camera:
    """World frame: X across the road (m, + right), Y along the road (+ away), Z up; camera at (x, 0, height)."""

    width: int = 640
    height_px: int = 480
    focal_px: float = 704.0
    height_m: float = 10.0
    tilt_deg: float = 16.0  # downwards from horizontal
    pan_deg: float = 0.0  # + turns the view to the right
    x_m: float = 0.0

    @cached_property
    def centre(self) -> np.ndarray:
        return np.array([self.x_m, 0.0, self.height_m])

    @cached_property
    def rotation(self) -> np.ndarray:
        """Rows: camera right, down, forward, in world coordinates."""
        th, ps = math.radians(self.tilt_deg), math.radians(self.pan_deg)
        f = np.array([math.sin(ps) * math.cos(th), math.cos(ps) * math.cos(th), -math.sin(th)])
        r = np.array([math.cos(ps), -math.sin(ps), 0.0])
        d = np.cross(f, r)
        return np.stack([r, d, f])

    @cached_property
    def K(self) -> np.ndarray:
        return np.array(
            [[self.focal_px, 0.0, self.width / 2.0], [0.0, self.focal_px, self.height_px / 2.0], [0.0, 0.0, 1.0]]
        )

    @cached_property
    def _P(self) -> np.ndarray:
        """3x4 projection matrix K [R | -R C]."""
        R = self.rotation
        return self.K @ np.column_stack([R, -R @ self.centre])

    def to_camera(self, pts: np.ndarray) -> np.ndarray:
        """(..., 3) world points -> (..., 3) camera coordinates (z = depth along the optical axis)."""
        return (np.asarray(pts, dtype=np.float64) - self.centre) @ self.rotation.T

    def project(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(..., 3) world points -> ((..., 2) pixels, (...) depth). Points behind the camera get depth <= 0."""
        P = self._P
        h = pts @ P[:, :3].T + P[:, 3]
        z = h[..., 2]
        zs = np.maximum(z, 1e-3)[..., None]
        return h[..., :2] / zs, z

    def road_to_image_matrix(self) -> np.ndarray:
        """3x3 homography mapping road (X, Y, 1) on Z = 0 to image pixels."""
        R = self.rotation
        M = np.column_stack([R[:, 0], R[:, 1], -R @ self.centre])
        H = self.K @ M
        return H / H[2, 2]

    def image_to_road(self, px: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, 2) road metres on Z = 0."""
        Hi = np.linalg.inv(self.road_to_image_matrix())
        p = np.asarray(px, dtype=np.float64).reshape(-1, 2)
        q = p @ Hi[:, :2].T + Hi[:, 2]
        return q[:, :2] / q[:, 2:3]

    def road_to_image(self, pts: np.ndarray) -> np.ndarray:
        p = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
        P = np.column_stack([p, np.zeros(len(p))])
        return self.project(P)[0]

    def horizon_row(self) -> float:
        return self.height_px / 2.0 - self.focal_px * math.tan(math.radians(self.tilt_deg))

    def scaled(self, factor: float) -> "Camera":
        """The same view at another resolution."""
        return Camera(
            width=int(round(self.width * factor)),
            height_px=int(round(self.height_px * factor)),
            focal_px=self.focal_px * factor,
            height_m=self.height_m,
            tilt_deg=self.tilt_deg,
            pan_deg=self.pan_deg,
            x_m=self.x_m,
        )
