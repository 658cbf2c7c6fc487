"""Corner detection in the detection zones: minimum eigenvalue of the structure tensor, NMS, spacing.

Only moving texture is searched (frame-difference mask), so static road markings rarely start features.
"""

from __future__ import annotations

import cv2
import numpy as np
from numba import njit

from appliance.config import TrackingParams

MOTION_LEVEL = 10  # grey levels of frame difference that count as motion
MOTION_GROW_PX = 7  # motion mask dilation, so corners at the edge of moving texture are kept
# The corner threshold is for daylight. In a frame dimmer on average than DAY_GREY (day scenes: 90-140, dusk:
# 50-60) a texture's contrast is dimmed with the light, and the structure tensor with the contrast squared, so
# the threshold falls with the mean grey squared (at dusk a far lane's cars would otherwise hold 1-3 features),
# but no lower than MIN_DIM_SCALE of it: the sensor's noise does not dim. (At night vehicles are found by their
# lights, which are not dim: the pipeline keeps the threshold there.)
DAY_GREY = 80.0
MIN_DIM_SCALE = 0.5


def dim_scale(mean_grey: float) -> float:
    """The share of the configured corner threshold that applies in a frame of this mean grey level."""
    return min(1.0, max(MIN_DIM_SCALE, (mean_grey / DAY_GREY) ** 2))


@njit(cache=True)
def select_spaced(cand_xy, live_xy, spacing, max_n, out):
    """Greedy pick from candidates sorted by decreasing score, each at least ``spacing`` px (Chebyshev)
    from every live feature and every earlier pick. Writes candidate indices to out; returns the count."""
    n = 0
    for c in range(cand_xy.shape[0]):
        if n >= max_n:
            break
        x = cand_xy[c, 0]
        y = cand_xy[c, 1]
        ok = True
        for j in range(live_xy.shape[0]):
            if abs(live_xy[j, 0] - x) < spacing and abs(live_xy[j, 1] - y) < spacing:
                ok = False
                break
        if ok:
            for k in range(n):
                o = out[k]
                if abs(cand_xy[o, 0] - x) < spacing and abs(cand_xy[o, 1] - y) < spacing:
                    ok = False
                    break
        if ok:
            out[n] = c
            n += 1
    return n


class CornerDetector:
    """Finds new corner features inside a fixed ROI with a zone mask."""

    BLOCK = 5  # structure tensor window (px)
    MAX_CANDIDATES_FACTOR = 8

    def __init__(self, params: TrackingParams, roi: tuple[int, int, int, int], zone_mask: np.ndarray) -> None:
        self.p = params
        self.roi = roi
        self.zone_mask = zone_mask  # uint8 0/255, ROI-sized
        self.kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * MOTION_GROW_PX + 1, 2 * MOTION_GROW_PX + 1))
        self.out = np.zeros(params.corners_per_frame, np.int64)
        self.last_score: np.ndarray | None = None
        self.scale = 1.0  # the share of the corner threshold that applies (see dim_scale)

    def motion_mask(self, cur_roi: np.ndarray, prev_roi: np.ndarray) -> np.ndarray:
        diff = cv2.absdiff(cur_roi, prev_roi)
        _, m = cv2.threshold(diff, MOTION_LEVEL, 255, cv2.THRESH_BINARY)
        return cv2.dilate(m, self.kernel)

    def detect(self, img: np.ndarray, prev: np.ndarray | None, live_px: np.ndarray, shift: tuple[int, int] = (0, 0),
               zone: tuple[tuple[int, int, int, int], np.ndarray] | None = None) -> np.ndarray:
        """New corner positions (N, 2) in full-image pixels, best first. ``shift`` moves the zones with
        the camera (integer px); ``zone`` (ROI, its mask) searches there instead of the detection zones."""
        x0, y0, x1, y1 = self.roi if zone is None else zone[0]
        zone_mask = self.zone_mask if zone is None else zone[1]
        sx, sy = shift
        h, w = img.shape
        x0s, x1s = min(max(0, x0 + sx), w - 1), min(max(1, x1 + sx), w)
        y0s, y1s = min(max(0, y0 + sy), h - 1), min(max(1, y1 + sy), h)
        cur = img[y0s:y1s, x0s:x1s]
        mask = zone_mask[y0s - y0 - sy : y1s - y0 - sy, x0s - x0 - sx : x1s - x0 - sx]
        if mask.shape != cur.shape or cur.size == 0:
            return np.zeros((0, 2))
        if prev is not None:
            mask = cv2.bitwise_and(mask, self.motion_mask(cur, prev[y0s:y1s, x0s:x1s]))
        # score only the bounding box of the moving part of the zones
        bx, by, bw, bh = cv2.boundingRect(mask)
        if bw < 8 or bh < 8:
            return np.zeros((0, 2))
        cur = cur[by : by + bh, bx : bx + bw]
        mask = mask[by : by + bh, bx : bx + bw]
        x0s += bx
        y0s += by
        score = cv2.cornerMinEigenVal(cur, self.BLOCK, 3)
        self.last_score = score
        peak = cv2.dilate(score, None)  # 3x3 non-maximum suppression
        good = (score >= self.p.corner_min_eig * self.scale) & (score >= peak) & (mask > 0)
        ys, xs = np.nonzero(good)
        # keep away from the image border so the template fits
        b = self.p.template_px // 2 + 1
        inside = (xs + x0s >= b) & (xs + x0s < w - b) & (ys + y0s >= b) & (ys + y0s < h - b)
        ys, xs = ys[inside], xs[inside]
        if len(xs) == 0:
            return np.zeros((0, 2))
        sc = score[ys, xs]
        order = np.argsort(-sc)[: self.p.corners_per_frame * self.MAX_CANDIDATES_FACTOR]
        cand = np.stack([xs[order] + x0s, ys[order] + y0s], axis=1).astype(np.float64)
        live = np.ascontiguousarray(live_px, dtype=np.float64).reshape(-1, 2)
        n = select_spaced(cand, live, float(self.p.corner_spacing_px), self.p.corners_per_frame, self.out)
        return cand[self.out[:n]]
