"""Drawing the site over a snapshot with cv2: lanes, zones, loops, fiducials and a metre grid,
in fixed colours per kind (COLOURS; the field guide lists them)."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import ArrayLike

from appliance.config import SiteConfig, clip_polygon_y, working_size
from appliance.geometry import Homography

# BGR, as cv2 uses them; docs/field-guide.md lists them for installers
COLOURS: dict[str, tuple[int, int, int]] = {
    "lane": (0, 200, 0),
    "detection": (0, 220, 255),
    "exit": (255, 0, 255),
    "count_line": (0, 140, 255),
    "loop": (0, 0, 255),
    "fiducial": (255, 255, 0),
    "grid": (255, 255, 255),
    "checker": (255, 128, 0),
    "calibration": (255, 0, 0),
}
LANE_ALPHA = 0.35
LOOP_ALPHA = 0.55
CHECKER_ALPHA = 0.25


def to_bgr(image: np.ndarray) -> np.ndarray:
    """A BGR uint8 copy of a grey or colour image."""
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    return image[:, :, :3].copy()


def blank(width: int, height: int, level: int = 64) -> np.ndarray:
    """A flat grey BGR image (used when there is no snapshot)."""
    return np.full((height, width, 3), level, np.uint8)


def _fill(img: np.ndarray, polys: list[np.ndarray], colour, alpha: float) -> None:
    if not polys:
        return
    layer = img.copy()
    cv2.fillPoly(layer, [np.round(p).astype(np.int32) for p in polys], colour, cv2.LINE_AA)
    mask = np.zeros(img.shape[:2], np.uint8)
    cv2.fillPoly(mask, [np.round(p).astype(np.int32) for p in polys], 255)
    blended = cv2.addWeighted(layer, alpha, img, 1.0 - alpha, 0.0)
    img[mask > 0] = blended[mask > 0]


def _outline(img: np.ndarray, poly: np.ndarray, colour, thickness: int = 1) -> None:
    cv2.polylines(img, [np.round(poly).astype(np.int32)], True, colour, thickness, cv2.LINE_AA)


def _label(img: np.ndarray, text: str, at, colour) -> None:
    x, y = int(round(at[0])), int(round(at[1]))
    scale = max(0.3, min(img.shape[1] / 1600.0, 0.8))
    cv2.putText(img, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(img, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, colour, 1, cv2.LINE_AA)


def lane_polygons_px(cfg: SiteConfig) -> dict[int, np.ndarray]:
    """Each lane's polygon in image pixels."""
    H = cfg.homography
    return {lane.id: H.road_to_img(np.asarray(lane.polygon_m)) for lane in cfg.lanes}


def loop_polygons_px(cfg: SiteConfig) -> dict[str, np.ndarray]:
    """Each loop's polygon in image pixels."""
    H = cfg.homography
    return {lp.id: H.road_to_img(np.asarray(lp.polygon_m)) for lp in cfg.loops}


def zone_polygons_px(cfg: SiteConfig, kind: str) -> dict[int, np.ndarray]:
    """Effective detection ("detection") or exit ("exit") zone per lane, in pixels: the
    configured range, or the default the service derives from the lane's direction."""
    from appliance.zones import SiteZones

    out = {}
    for lz in SiteZones(cfg).lanes:
        poly = lz.detection_px if kind == "detection" else lz.exit_px
        if len(poly) >= 3:
            out[lz.lane_id] = np.asarray(poly, dtype=np.float64)
    return out


def draw_site(image: np.ndarray, cfg: SiteConfig, labels: bool = True) -> np.ndarray:
    """The snapshot with lanes, detection/exit zones, count lines, loops and fiducials drawn on it."""
    img = to_bgr(image)
    H = cfg.homography
    lanes = lane_polygons_px(cfg)
    _fill(img, list(lanes.values()), COLOURS["lane"], LANE_ALPHA)
    for poly in lanes.values():
        _outline(img, poly, COLOURS["lane"], 2)
    for kind, colour in (("detection", COLOURS["detection"]), ("exit", COLOURS["exit"])):
        for lane_id, poly in zone_polygons_px(cfg, kind).items():
            _outline(img, poly, colour, 1)
            if labels:
                _label(img, "det" if kind == "detection" else "exit", poly.mean(axis=0) + [-8, 4], colour)
    for lane in cfg.lanes:
        xs = np.asarray(lane.polygon_m)[:, 0]
        seg = clip_polygon_y(np.asarray(lane.polygon_m), lane.count_y_m - 1e-3, lane.count_y_m + 1e-3)
        x0, x1 = (seg[:, 0].min(), seg[:, 0].max()) if len(seg) else (xs.min(), xs.max())
        line = H.road_to_img([[x0, lane.count_y_m], [x1, lane.count_y_m]])
        cv2.line(img, tuple(np.round(line[0]).astype(int)), tuple(np.round(line[1]).astype(int)),
                 COLOURS["count_line"], 1, cv2.LINE_AA)
    loops = loop_polygons_px(cfg)
    _fill(img, list(loops.values()), COLOURS["loop"], LOOP_ALPHA)
    for lp in cfg.loops:
        _outline(img, loops[lp.id], COLOURS["loop"], 1)
    if labels:
        for lane_id, poly in lanes.items():
            bottom = poly[np.argmax(poly[:, 1])]
            centre = poly.mean(axis=0)
            at = 0.5 * (bottom + centre)
            _label(img, f"lane {lane_id}", (at[0] - 20, at[1]), COLOURS["lane"])
        for lp in cfg.loops:
            poly = loops[lp.id]
            _label(img, f"{lp.id} ch{lp.channel}", (poly[:, 0].max() + 3, poly[:, 1].mean() + 4), COLOURS["loop"])
    # the patch around each fiducial, in the camera's pixels (the stabiliser works at the working size)
    half = round((cfg.tracking.template_px // 2 + 4) * cfg.source.width / working_size(cfg)[0])
    for i, (u, v) in enumerate(cfg.fiducials):
        c = (int(round(u)), int(round(v)))
        cv2.drawMarker(img, c, COLOURS["fiducial"], cv2.MARKER_CROSS, 2 * half, 1, cv2.LINE_AA)
        cv2.rectangle(img, (c[0] - half, c[1] - half), (c[0] + half, c[1] + half), COLOURS["fiducial"], 1)
        if labels:
            _label(img, f"F{i + 1}", (c[0] + half + 2, c[1] - half), COLOURS["fiducial"])
    return img


def _in_front(H: Homography, pts_m: np.ndarray) -> np.ndarray:
    """True where road points are in front of the camera (same side of the horizon as the image)."""
    p = np.asarray(pts_m, dtype=np.float64).reshape(-1, 2)
    w = p @ H.Hinv[2, :2] + H.Hinv[2, 2]
    return w > 1e-9


def grid_lines_m(x_range: tuple[float, float], y_range: tuple[float, float], step_x: float = 1.0, step_y: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    """Positions of the grid lines: X values (along-road lines) and Y values (cross-road lines)."""
    xs = np.arange(np.floor(x_range[0] / step_x) * step_x, x_range[1] + 1e-9, step_x)
    ys = np.arange(np.floor(y_range[0] / step_y) * step_y, y_range[1] + 1e-9, step_y)
    return xs, ys


def draw_grid(
    image: np.ndarray,
    H: Homography,
    x_range: tuple[float, float],
    y_range: tuple[float, float],
    step_x: float = 1.0,
    step_y: float = 5.0,
    checker: bool = True,
    labels: bool = True,
) -> np.ndarray:
    """A metre grid (and checkerboard) on the road plane, projected into the snapshot with H."""
    img = to_bgr(image)
    h, w = img.shape[:2]
    xs, ys = grid_lines_m(x_range, y_range, step_x, step_y)
    if checker and len(xs) > 1 and len(ys) > 1:
        cells = []
        for i in range(len(xs) - 1):
            for j in range(len(ys) - 1):
                if (i + j) % 2:
                    continue
                quad = np.array([[xs[i], ys[j]], [xs[i + 1], ys[j]], [xs[i + 1], ys[j + 1]], [xs[i], ys[j + 1]]])
                if _in_front(H, quad).all():
                    px = H.road_to_img(quad)
                    if np.all(np.abs(px) < 4 * (w + h)):
                        cells.append(px)
        _fill(img, cells, COLOURS["checker"], CHECKER_ALPHA)
    n = 200
    lines = [np.column_stack([np.full(n, x), np.linspace(ys[0], ys[-1], n)]) for x in xs]
    lines += [np.column_stack([np.linspace(xs[0], xs[-1], n), np.full(n, y)]) for y in ys]
    for line in lines:
        ok = _in_front(H, line)
        px = H.road_to_img(line)
        ok &= np.all(np.abs(px) < 4 * (w + h), axis=1)
        px = px[ok]
        if len(px) >= 2:
            cv2.polylines(img, [np.round(px).astype(np.int32)], False, COLOURS["grid"], 1, cv2.LINE_AA)
    if labels:
        for y in ys:
            p = H.road_to_img([[xs[-1], y]])[0]
            if _in_front(H, [[xs[-1], y]])[0] and 0 <= p[0] < w - 10 and 0 <= p[1] < h:
                _label(img, f"{y:g} m", (p[0] + 3, p[1] + 4), COLOURS["grid"])
    return img


def draw_calibration_points(image: np.ndarray, image_px: ArrayLike, errors_m: ArrayLike) -> np.ndarray:
    """Calibration points as circles labelled with their reprojection error in metres."""
    img = to_bgr(image)
    for (u, v), e in zip(np.asarray(image_px, dtype=float), np.asarray(errors_m, dtype=float)):
        c = (int(round(u)), int(round(v)))
        cv2.circle(img, c, 4, COLOURS["calibration"], 1, cv2.LINE_AA)
        _label(img, f"{e:.2f}", (c[0] + 5, c[1] - 4), COLOURS["calibration"])
    return img
