"""Per-lane detection and exit zones (road metres and image masks), defaulted from each lane's direction.

Approaching lanes (Y decreasing) enter at the far end (top of the image) and leave near the camera;
receding lanes the reverse. Features are detected at the entry end, vehicles finalised at the exit end.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from appliance.config import SiteConfig, clip_polygon_y
from appliance.geometry import Homography

# features further than this beyond their lane's along-road extent are dropped (pipeline) and not searched for
# off the lanes (SiteZones._lifted)
LANE_MARGIN_M = 2.0
DETECTION_ROW_SHARE = 0.7  # share of the rows between the entry edge and the count line where features start
EXIT_ROW_SHARE = 0.12  # exit share of the lane's image rows where vehicles are finalised
TALLEST_M = 4.5  # the tallest vehicle: bounds how much further its top is seen than the road under it
MAX_GAIN = 2.5  # ... by at most this factor (a camera barely above the tallest vehicle, or of unknown height)


@dataclass
class LaneZones:
    """One lane's zones. ``sign`` is +1 for receding (Y increasing), -1 for approaching."""

    lane_id: int
    index: int  # 1-based label used in the lane image
    sign: int
    polygon_m: np.ndarray
    y_extent: tuple[float, float]
    detection_y: tuple[float, float]
    exit_y: tuple[float, float]
    count_y: float
    region_y: tuple[float, float]  # the Edie region along the road
    polygon_px: np.ndarray
    detection_px: np.ndarray
    exit_px: np.ndarray

    def in_detection(self, y: float) -> bool:
        """Whether along-road position y lies in the detection zone."""
        return self.detection_y[0] <= y <= self.detection_y[1]

    def in_exit(self, y: float) -> bool:
        """Whether a vehicle's representative point at along-road position y has reached the exit zone."""
        return y <= self.exit_y[1] if self.sign < 0 else y >= self.exit_y[0]


def _y_at_row(H: Homography, poly_px: np.ndarray, row: float) -> float:
    """Along-road Y at an image row, taken at the lane's middle column."""
    cx = float(poly_px[:, 0].mean())
    return float(H.img_to_road([[cx, row]])[0, 1])


def _default_ranges(H: Homography, poly_px: np.ndarray, ylo: float, yhi: float, sign: int, count_y: float):
    """Detection from the entry edge to DETECTION_ROW_SHARE of the way (in image rows) to the count line, so
    vehicles are grouped before they are counted; exit over the last EXIT_ROW_SHARE of the lane's rows."""
    top, bottom = float(poly_px[:, 1].min()), float(poly_px[:, 1].max())
    span = bottom - top
    cx = float(poly_px[:, 0].mean())
    count_row = float(H.road_to_img([[float(H.img_to_road([[cx, 0.5 * (top + bottom)]])[0, 0]), count_y]])[0, 1])
    count_row = min(max(count_row, top), bottom)
    far_exit = _y_at_row(H, poly_px, top + EXIT_ROW_SHARE * span)
    near_exit = _y_at_row(H, poly_px, bottom - EXIT_ROW_SHARE * span)
    if sign < 0:  # approaching: enters at the top (far), detect there, finalise near the camera
        det_end = _y_at_row(H, poly_px, top + DETECTION_ROW_SHARE * max(count_row - top, 0.2 * span))
        det = (max(ylo, min(det_end, yhi - 1.0)), yhi)
        ext = (ylo, max(ylo + 0.5, min(near_exit, yhi)))
    else:
        det_end = _y_at_row(H, poly_px, bottom - DETECTION_ROW_SHARE * max(bottom - count_row, 0.2 * span))
        det = (ylo, min(yhi, max(det_end, ylo + 1.0)))
        ext = (min(yhi - 0.5, max(far_exit, ylo)), yhi)
    return det, ext


def _zone_roi(img: np.ndarray, margin: int = 4) -> tuple[tuple[int, int, int, int], np.ndarray] | None:
    """The ROI (x0, y0, x1, y1) of a zone image's non-zero pixels, with room for the corner window, and the
    zone's 0/255 mask over it; None for an empty zone."""
    ys, xs = np.nonzero(img)
    if len(xs) == 0:
        return None
    h, w = img.shape
    x0, y0 = max(0, int(xs.min()) - margin), max(0, int(ys.min()) - margin)
    x1, y1 = min(w, int(xs.max()) + margin + 1), min(h, int(ys.max()) + margin + 1)
    return (x0, y0, x1, y1), np.ascontiguousarray((img[y0:y1, x0:x1] > 0).astype(np.uint8) * 255)


def _poly_px(H: Homography, poly_m: np.ndarray, y0: float, y1: float) -> np.ndarray:
    part = clip_polygon_y(poly_m, y0, y1)
    if len(part) < 3:
        return np.zeros((0, 2))
    return H.road_to_img(part)


class SiteZones:
    """All lanes' zones plus the image masks the stages need (built once per site and frame size)."""

    def __init__(self, site: SiteConfig) -> None:
        H = site.homography
        if H is None:
            raise ValueError("site config is not validated: no homography (use appliance.config.parse_site)")
        self.H = H
        self.width, self.height = int(site.source.width), int(site.source.height)
        self.lanes: list[LaneZones] = []
        for i, lane in enumerate(site.lanes):
            poly = np.asarray(lane.polygon_m, dtype=np.float64)
            ylo, yhi = float(poly[:, 1].min()), float(poly[:, 1].max())
            sign = -1 if lane.direction == "approaching" else 1
            poly_px = H.road_to_img(poly)
            count_y = float(lane.count_y_m) if lane.count_y_m is not None else 0.5 * (ylo + yhi)
            det, ext = _default_ranges(H, poly_px, ylo, yhi, sign, count_y)
            region = (float(lane.region_y_m[0]), float(lane.region_y_m[1])) if lane.region_y_m else (ylo, yhi)
            if lane.detection_y_m is not None:
                det = (float(lane.detection_y_m[0]), float(lane.detection_y_m[1]))
            if lane.exit_y_m is not None:
                ext = (float(lane.exit_y_m[0]), float(lane.exit_y_m[1]))
            self.lanes.append(
                LaneZones(
                    lane_id=lane.id,
                    index=i + 1,
                    sign=sign,
                    polygon_m=poly,
                    y_extent=(ylo, yhi),
                    detection_y=det,
                    exit_y=ext,
                    count_y=count_y,
                    region_y=region,
                    polygon_px=poly_px,
                    detection_px=_poly_px(H, poly, *det),
                    exit_px=_poly_px(H, poly, *ext),
                )
            )
        self.camera = camera_from_homography(H, self.width, self.height)
        self.k_max = top_gain(self.camera)
        self.length_camera = self.camera if self.camera is not None else length_camera(H, self.width, self.height)
        self.length_k_max = top_gain(self.length_camera)
        self.lane_image = self._paint("polygon_px")  # 0 = no lane, else LaneZones.index
        self.detection_image = self._paint("detection_px")
        self.exit_image = self._paint("exit_px")
        self.lifted_image = self._lifted()
        detection = _zone_roi(self.detection_image)
        if detection is None:
            raise ValueError("no detection zone falls inside the image")
        # ROI (x0, y0, x1, y1) of all detection zones, with room for the corner window, and their mask over it
        self.detection_roi, self.detection_mask_roi = detection
        self.lifted_zone = _zone_roi(self.lifted_image)  # (ROI, its mask) or None
        self.sign_by_index = np.array([0] + [lz.sign for lz in self.lanes], dtype=np.int32)
        self.lane_extent_by_index = np.array([[0.0, 0.0]] + [list(lz.y_extent) for lz in self.lanes])

    def magnification(self, height_m: float) -> float | None:
        """_gain of the tracker's camera."""
        return _gain(self.camera, height_m)

    def length_magnification(self, height_m: float) -> float | None:
        """_gain of the camera that lengths are measured with (length_camera)."""
        return _gain(self.length_camera, height_m)

    def _paint(self, attr: str) -> np.ndarray:
        img = np.zeros((self.height, self.width), np.uint8)
        for lz in self.lanes:
            pts = getattr(lz, attr)
            if len(pts) >= 3:
                cv2.fillPoly(img, [np.round(pts).astype(np.int32)], int(lz.index))
        return img

    def _lifted(self) -> np.ndarray:
        """Off the lanes, where the tops of vehicles in a lane's detection zone are seen (an approaching truck's
        box beyond the far lane, leaning away from the camera): that lane's index, else 0. Where two lanes' tops
        may be seen, the lane further from the camera's foot across the road (nearer there). All 0 without a
        camera."""
        img = np.zeros((self.height, self.width), np.uint8)
        if self.camera is None:
            return img
        foot = np.array(self.camera[:2])
        for lz in sorted(self.lanes, key=lambda lz: abs(float(lz.polygon_m[:, 0].mean()) - foot[0])):
            part = clip_polygon_y(lz.polygon_m, *lz.detection_y)
            if len(part) < 3:
                continue
            hull = cv2.convexHull(np.concatenate([part, foot + (part - foot) * self.k_max]).astype(np.float32))
            # only where a corner's projected place lies within the lane's along-road extent plus LANE_MARGIN_M:
            # beyond it the pipeline drops the feature the next frame, so searching there only spends corners
            hull = clip_polygon_y(hull.reshape(-1, 2), lz.y_extent[0] - LANE_MARGIN_M,
                                  lz.y_extent[1] + LANE_MARGIN_M)
            if len(hull) < 3:
                continue
            cv2.fillPoly(img, [np.round(self.H.road_to_img(hull)).astype(np.int32)], int(lz.index))
        img[self.lane_image > 0] = 0
        return img

    def lane_at_px(self, px: np.ndarray, lifted: bool = False) -> np.ndarray:
        """Lane index (0 = none) under each image point (N, 2); with lifted, off the lanes the lane whose
        vehicles' tops may be seen there (see _lifted)."""
        p = np.asarray(px).reshape(-1, 2)
        x = np.clip(np.round(p[:, 0]).astype(np.int64), 0, self.width - 1)
        y = np.clip(np.round(p[:, 1]).astype(np.int64), 0, self.height - 1)
        lane = self.lane_image[y, x].astype(np.int32)
        return np.where(lane > 0, lane, self.lifted_image[y, x]) if lifted else lane

    def lane_at_road(self, x: float, y: float) -> LaneZones | None:
        """The lane whose road polygon holds road point (x, y), or None."""
        for lz in self.lanes:
            if cv2.pointPolygonTest(lz.polygon_m.astype(np.float32), (float(x), float(y)), False) >= 0:
                return lz
        return None

    def by_index(self, index: int) -> LaneZones:
        return self.lanes[index - 1]


def _gain(camera: tuple[float, float, float] | None, height_m: float) -> float | None:
    """How many times further from the camera's foot (camera: foot X, Y, height) a point this high above the road
    is seen than the road under it; None without a camera, or with one not well above that height."""
    h = camera[2] if camera is not None else 0.0
    return h / (h - height_m) if h > height_m + 0.5 else None


def top_gain(camera: tuple[float, float, float] | None) -> float:
    """How many times further a vehicle's top is seen than the road under it, at most (see MAX_GAIN)."""
    k = _gain(camera, TALLEST_M)
    return MAX_GAIN if k is None else min(MAX_GAIN, k)


MAX_FOCAL_DISAGREEMENT = 3.0  # see camera_from_homography
MIN_AXES_COSINE = 0.05  # ditto
CAMERA_HEIGHT_M = (3.0, 60.0)  # a plausible pole or overpass camera
# Half a pixel of click error moves the column that fits (see _principal_column) by up to 0.06 of the width
# (90 % of calibrations, panned 2-20 degrees): beyond this share the frame is taken as a crop
CROP_SHARE = 0.1


def _centred(H: Homography, width: int, height: int) -> np.ndarray:
    """The road-to-image homography in image widths from the image centre (the pinhole constraints on its
    columns then weigh alike)."""
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    s = float(width)
    return np.diag([1 / s, 1 / s, 1.0]) @ np.array([[1, 0, -cx], [0, 1, -cy], [0, 0, 1]], dtype=np.float64) @ H.Hinv


def camera_from_homography(H: Homography, width: int, height: int) -> tuple[float, float, float] | None:
    """Camera foot (X, Y) on the road and height (m), assuming square pixels and the principal point at
    the image centre. None when the homography does not fit such a camera on a pole or overpass
    (CAMERA_HEIGHT_M), or does not fix how far away the camera is."""
    s = float(width)
    A = _centred(H, width, height)
    a1, a2 = A[:, 0], A[:, 1]
    # The road's X and Y axes seen through K^-1 are orthogonal and of equal length, each linear in w = 1 / f^2:
    # c w + d = 0. Least squares over both weighs each by how much it says: the first one's terms both shrink
    # as the camera's pan does, and click errors of half a pixel move its w by 40 % at a pan of 8 degrees.
    c = np.array([a1[0] * a2[0] + a1[1] * a2[1], a1[0] ** 2 + a1[1] ** 2 - a2[0] ** 2 - a2[1] ** 2])
    d = np.array([a1[2] * a2[2], a1[2] ** 2 - a2[2] ** 2])
    w = -float(c @ d) / float(c @ c) if float(c @ c) > 1e-30 else -1.0
    if not np.isfinite(w) or w <= 0:
        return None
    # The second one alone holds for any along-road scale (a focal length to match each). The first one says
    # how far the camera's axis turns from the road's (its terms shrink together as the pan does): where the
    # road's axes are far from perpendicular in the image (cosine over MIN_AXES_COSINE) and it gives a focal
    # length more than MAX_FOCAL_DISAGREEMENT times the fit's, no camera with its principal point at the image
    # centre fits (a cropped frame; a calibration from assumed marking standards: a real overpass clip gave 15
    # times). A negative w there is click errors' noise.
    cos = abs(c[0]) / (np.hypot(a1[0], a1[1]) * np.hypot(a2[0], a2[1]) + 1e-30)
    w1 = -d[0] / c[0] if abs(c[0]) > 1e-30 else 0.0
    if cos > MIN_AXES_COSINE and w1 > 0 and max(w1 / w, w / w1) > MAX_FOCAL_DISAGREEMENT ** 2:
        return None
    return _camera_pose(np.diag([s, s, 1.0]) @ A, s / np.sqrt(w))


def length_camera(H: Homography, width: int, height: int) -> tuple[float, float, float] | None:
    """The camera (foot X, Y, height) that lengths and tops' speeds are judged with: the centred one, else one
    placed off-centre (see placed_camera); the tracker undoes heights only with the centred one."""
    cam = camera_from_homography(H, width, height)
    if cam is None and (placed := placed_camera(H, width, height)) is not None:
        cam = placed[:3]
    return cam


def placed_camera(H: Homography, width: int, height: int) -> tuple[float, float, float, float] | None:
    """Camera foot (X, Y), height (m) and the column its lens's axis passes through: camera_from_homography's
    (the centre column), or, where the column that fits exactly (on the middle row) lies more than CROP_SHARE
    of the width from the centre or no centred camera fits, the camera with its principal point at that column
    (a frame cropped left or right of the lens's axis; or an along-road scale somewhat out). None when neither
    fits a camera on a pole or overpass. For the installer (roadwatch calibrate) and for lengths
    (SiteZones.length_camera): the tracker undoes heights only with a centred camera. (On the real clip, column
    276 of 320, tracking with this camera counted worse: 7 of 15 variants within 1 vehicle per lane, against 10
    without heights.)"""
    col = _principal_column(H, width, height)
    cropped = col is not None and abs(col[0] - (width - 1) / 2.0) > CROP_SHARE * width
    cam = None if cropped else camera_from_homography(H, width, height)
    if cam is not None:
        return (*cam, (width - 1) / 2.0)
    if col is None:
        return None
    T = np.array([[1, 0, -col[0]], [0, 1, -(height - 1) / 2.0], [0, 0, 1]], dtype=np.float64)
    cam = _camera_pose(T @ H.Hinv, col[1])
    return None if cam is None else (*cam, col[0])


def _principal_column(H: Homography, width: int, height: int) -> tuple[float, float] | None:
    """The principal point's column (inside the image) and focal length (px) that fit both pinhole
    constraints exactly, the principal point on the middle row: with the image of the absolute conic
    [[1, 0, -u], [0, 1, 0], [-u, 0, f^2 + u^2]] (u the column's offset from the centre) both are linear in u and
    f^2 + u^2. A frame cropped left or right of the lens's axis fits one; so does a calibration whose
    along-road scale is somewhat out (it moves the column, hardly the height), a grossly wrong one not."""
    cx = (width - 1) / 2.0
    s = float(width)
    A = _centred(H, width, height)
    a1, a2 = A[:, 0], A[:, 1]

    def terms(a: np.ndarray, b: np.ndarray) -> np.ndarray:  # a^T omega b: constant, -u and (f^2 + u^2) terms
        return np.array([a[0] * b[0] + a[1] * b[1], a[0] * b[2] + a[2] * b[0], a[2] * b[2]])

    e1, e2 = terms(a1, a2), terms(a1, a1) - terms(a2, a2)
    M = np.array([[e1[1], e1[2]], [e2[1], e2[2]]])
    if abs(np.linalg.det(M)) < 1e-18:
        return None
    w13, w33 = np.linalg.solve(M, -np.array([e1[0], e2[0]]))
    u = -float(w13)
    f2 = float(w33) - u * u
    col = cx + u * s
    if not np.isfinite(f2) or f2 <= 0 or not 0.0 <= col <= width - 1:
        return None
    return col, float(np.sqrt(f2)) * s


def _camera_pose(A: np.ndarray, f: float) -> tuple[float, float, float] | None:
    """Camera foot (X, Y) and height for focal length f (px), A the road-to-image homography in pixels from the
    principal point; None if implausible."""
    a1, a2, a3 = A[:, 0], A[:, 1], A[:, 2]
    Kinv = np.diag([1 / f, 1 / f, 1.0])
    b1, b2, b3 = Kinv @ a1, Kinv @ a2, Kinv @ a3
    lam = np.sqrt(np.linalg.norm(b1) * np.linalg.norm(b2))
    r1, r2 = b1 / np.linalg.norm(b1), b2 / np.linalg.norm(b2)
    r3 = np.cross(r1, r2)
    t = b3 / lam
    R = np.column_stack([r1, r2, r3])
    C = -R.T @ t
    if C[2] < 0:  # the other sign of lambda
        C = -R.T @ (-t)
        C[2] = abs(C[2])
    if not np.all(np.isfinite(C)) or not CAMERA_HEIGHT_M[0] <= C[2] <= CAMERA_HEIGHT_M[1]:
        return None
    return float(C[0]), float(C[1]), float(C[2])
