"""Camera calibration: the image <-> road-plane homography, its error in metres, and depth scale."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike


class CalibrationError(ValueError):
    """The correspondences cannot give a usable homography."""


def _as_points(points, name: str) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise CalibrationError(f"{name}: expected a list of [x, y] pairs, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise CalibrationError(f"{name}: contains a non-finite value")
    return arr


def _max_collinear_residual(pts: np.ndarray) -> float:
    """Largest distance of a point from the best-fit line, relative to the spread of the points."""
    c = pts - pts.mean(axis=0)
    _, s, _ = np.linalg.svd(c, full_matrices=False)
    return float(s[-1] / max(s[0], 1e-12))


@dataclass(frozen=True)
class Homography:
    """H maps image pixels to road metres; Hinv maps back."""

    H: np.ndarray
    Hinv: np.ndarray

    @classmethod
    def from_matrix(cls, H: ArrayLike) -> "Homography":
        H = np.asarray(H, dtype=np.float64).reshape(3, 3)
        if abs(np.linalg.det(H)) < 1e-12:
            raise CalibrationError("homography matrix is singular")
        return cls(H / H[2, 2], np.linalg.inv(H) / np.linalg.inv(H)[2, 2])

    @classmethod
    def from_points(cls, image_px: ArrayLike, road_m: ArrayLike) -> "Homography":
        img = _as_points(image_px, "calibration.image_px")
        road = _as_points(road_m, "calibration.road_m")
        if len(img) != len(road):
            raise CalibrationError(
                f"calibration: {len(img)} image points but {len(road)} road points; they must pair up"
            )
        if len(img) < 4:
            raise CalibrationError(f"calibration: needs at least 4 point pairs, got {len(img)}")
        if _max_collinear_residual(img) < 1e-3 or _max_collinear_residual(road) < 1e-3:
            raise CalibrationError("calibration: points are (nearly) collinear; the homography is degenerate")
        H, _ = cv2.findHomography(img, road, 0)
        if H is None or not np.all(np.isfinite(H)):
            raise CalibrationError("calibration: no homography fits these points (degenerate layout)")
        return cls.from_matrix(H)

    def img_to_road(self, pts: ArrayLike) -> np.ndarray:
        """(N, 2) pixels -> (N, 2) metres."""
        return _apply(self.H, pts)

    def road_to_img(self, pts: ArrayLike) -> np.ndarray:
        """(N, 2) metres -> (N, 2) pixels."""
        return _apply(self.Hinv, pts)

    def reprojection_error_m(self, image_px: ArrayLike, road_m: ArrayLike) -> np.ndarray:
        """Per-point distance in metres between the mapped image points and their road points."""
        return np.linalg.norm(self.img_to_road(image_px) - np.asarray(road_m, dtype=np.float64), axis=1)

    def metres_per_pixel(self, pts: ArrayLike) -> np.ndarray:
        """Depth scale at image points: (N, 2) metres per pixel along image x and y."""
        p = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
        r = self.img_to_road(p)
        dx = np.linalg.norm(self.img_to_road(p + [1.0, 0.0]) - r, axis=1)
        dy = np.linalg.norm(self.img_to_road(p + [0.0, 1.0]) - r, axis=1)
        return np.stack([dx, dy], axis=1)

    def horizon_row(self, column: float) -> float | None:
        """Image row of the road plane's vanishing line at an image column (None if not in view)."""
        a, b, c = self.H[2]
        if abs(b) < 1e-12:
            return None
        return float(-(a * column + c) / b)


def _apply(M: np.ndarray, pts) -> np.ndarray:
    p = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    q = p @ M[:, :2].T + M[:, 2]
    return q[:, :2] / q[:, 2:3]


def polygon_contains(poly: np.ndarray, pts: ArrayLike) -> np.ndarray:
    """Vectorised point-in-polygon test (even-odd rule). poly (M, 2), pts (N, 2) -> bool (N,)."""
    poly = np.asarray(poly, dtype=np.float64)
    p = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    x, y = p[:, 0:1], p[:, 1:2]
    x1, y1 = poly[:, 0], poly[:, 1]
    x2, y2 = np.roll(x1, -1), np.roll(y1, -1)
    cond = (y1 > y) != (y2 > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xint = x1 + (y - y1) * (x2 - x1) / (y2 - y1)
    return np.count_nonzero(cond & (x < xint), axis=1) % 2 == 1
