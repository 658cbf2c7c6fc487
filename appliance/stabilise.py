"""Camera stabilisation: subpixel NCC of fiducial templates against the first frame gives the image shift,
referred to the camera's rest position (the first frame is as shaken as any other).

Fiducials come from the site config, or are picked automatically (static textured points off the lanes).
"""

from __future__ import annotations

import cv2
import numpy as np

TEMPLATE_PX = 15
SEARCH_PX = 12  # search radius around the last offset (per-frame shake plus drift rate)
NCC_OK = 0.6  # below this a fiducial counts as occluded in this frame
AUTO_COUNT = 8
AUTO_SPACING_PX = 32
AUTO_CHECK_FRAMES = 10  # auto-picked fiducials must agree with the others in most of the first frames
MIN_AGREE = 2  # fiducials that must agree on a shift for it to be taken (while that many are usable)
LONE_STEP_PX = 1.0
# An auto-picked point's corner score (cornerMinEigenVal) must reach AUTO_NOISE_FACTOR times the frame's median
# score (its noise and fine texture) and AUTO_REL_SCORE times its strongest corners' (the 99.9th percentile): the
# scores scale with contrast squared, so an absolute bar picked nothing in dark, dusky, rainy or soft frames
AUTO_NOISE_FACTOR = 8.0
AUTO_REL_SCORE = 0.25
AUTO_MIN_EIG = 1e-4  # (a flat frame has nothing to pick)
# The first frame carries its own shake: the shift of the camera's rest position from it is the intercept of a
# straight line (rest position plus steady drift) through the shifts of the first REST_FRAMES frames, applied
# from REST_MIN_FRAMES on and at most REST_STEP_PX per frame, so tracked features never see it as motion.
REST_FRAMES = 750
REST_MIN_FRAMES = 50
REST_STEP_PX = 0.02


def _parabola(a: float, b: float, c: float) -> float:
    d = a - 2.0 * b + c
    if d >= 0:
        return 0.0
    return float(min(max(0.5 * (a - c) / d, -0.5), 0.5))


class Stabiliser:
    """``step(img)`` returns the offset (dx, dy): where a reference-frame point is now, minus where it was."""

    def __init__(self, fiducials: list[list[float]], lane_image: np.ndarray, enabled: bool = True) -> None:
        self.enabled = enabled
        self.configured = [tuple(map(float, f)) for f in fiducials]
        self.lane_image = lane_image
        self.points = np.zeros((0, 2))
        self.templates: list[np.ndarray] = []
        self.usable = np.zeros(0, np.bool_)
        self.offset = np.zeros(2)
        self.last_ncc = np.zeros(0)
        self.ok = np.zeros(0, np.bool_)
        self.frames = 0
        self.auto = not self.configured
        self.raw = np.zeros(2)  # the shift from the first frame
        self.rest = np.zeros(2)  # the rest position's shift from the first frame, as applied so far
        # sums over the first frames k = 0, 1, ... of the line fit: 1, k, k * k, shift, k * shift
        self._n = self._sk = self._skk = 0.0
        self._sy, self._sky = np.zeros(2), np.zeros(2)
        self._target: np.ndarray | None = None  # the fit's intercept (fixed once REST_FRAMES are in)

    def _pick(self, img: np.ndarray) -> list[tuple[float, float]]:
        h, w = img.shape
        keep_out = cv2.dilate((self.lane_image > 0).astype(np.uint8), np.ones((21, 21), np.uint8))
        score = cv2.cornerMinEigenVal(img, 7, 3)
        bar = max(AUTO_NOISE_FACTOR * float(np.median(score)), AUTO_REL_SCORE * float(np.percentile(score, 99.9)),
                  AUTO_MIN_EIG)
        m = SEARCH_PX + TEMPLATE_PX
        score[keep_out > 0] = 0
        score[:m, :] = 0
        score[-m:, :] = 0
        score[:, :m] = 0
        score[:, -m:] = 0
        picked: list[tuple[float, float]] = []
        order = np.argsort(-score, axis=None)[:5000]
        for flat in order:
            y, x = divmod(int(flat), w)
            if score[y, x] < bar:
                break
            if all(abs(x - px) >= AUTO_SPACING_PX or abs(y - py) >= AUTO_SPACING_PX for px, py in picked):
                picked.append((float(x), float(y)))
                if len(picked) >= AUTO_COUNT:
                    break
        return picked

    def _init(self, img: np.ndarray) -> None:
        pts = self.configured if self.configured else self._pick(img)
        h, w = img.shape
        r = TEMPLATE_PX // 2
        keep = []
        for x, y in pts:
            xi, yi = int(round(x)), int(round(y))
            if r <= xi < w - r and r <= yi < h - r:
                self.templates.append(img[yi - r : yi + r + 1, xi - r : xi + r + 1].copy())
                keep.append((xi, yi))
        self.points = np.array(keep, dtype=np.float64).reshape(-1, 2)
        self.usable = np.ones(len(keep), np.bool_)
        self._misses = np.zeros(len(keep), np.int64)  # first frames an auto-picked point disagreed in ...
        self._checks = np.zeros(len(keep), np.int64)  # ... and matched in
        self.last_ncc = np.zeros(len(keep))
        self.ok = np.zeros(len(keep), np.bool_)

    def step(self, img: np.ndarray) -> tuple[float, float]:
        if not self.enabled:
            return 0.0, 0.0
        if self.frames == 0:
            self._init(img)
        self.frames += 1
        h, w = img.shape
        r = TEMPLATE_PX // 2
        disp = np.full((len(self.points), 2), np.nan)
        for k, (x, y) in enumerate(self.points):
            if not self.usable[k]:
                self.ok[k] = False
                continue
            cx = int(round(x + self.raw[0]))
            cy = int(round(y + self.raw[1]))
            x0, y0 = cx - r - SEARCH_PX, cy - r - SEARCH_PX
            x1, y1 = cx + r + SEARCH_PX + 1, cy + r + SEARCH_PX + 1
            if x0 < 0 or y0 < 0 or x1 > w or y1 > h:
                self.ok[k] = False
                continue
            res = cv2.matchTemplate(img[y0:y1, x0:x1], self.templates[k], cv2.TM_CCOEFF_NORMED)
            _, best, _, (bx, by) = cv2.minMaxLoc(res)
            self.last_ncc[k] = best
            self.ok[k] = best >= NCC_OK
            if not self.ok[k]:
                continue
            sx = _parabola(res[by, bx - 1], best, res[by, bx + 1]) if 0 < bx < res.shape[1] - 1 else 0.0
            sy = _parabola(res[by - 1, bx], best, res[by + 1, bx]) if 0 < by < res.shape[0] - 1 else 0.0
            disp[k] = (x0 + bx + sx + r - x, y0 + by + sy + r - y)
        good = self.ok.copy()
        if good.any():
            med = np.median(disp[good], axis=0)
            # a fiducial disagreeing with the others by more than 1.5 px is moving or mismatched
            agree = good & (np.abs(disp - med).max(axis=1) <= 1.5)
            # one fiducial alone has nothing to check it against: a false match (rain streaks over its patch)
            # moved the offset and the next search with it, and it ran away by 100 px on a fixed camera. Where
            # it is the only one usable, it may move the offset by LONE_STEP_PX a frame at most.
            if agree.sum() >= MIN_AGREE:
                self.raw = disp[agree].mean(axis=0)
            elif agree.any() and self.usable.sum() < MIN_AGREE:
                self.raw = self.raw + np.clip(disp[agree].mean(axis=0) - self.raw, -LONE_STEP_PX, LONE_STEP_PX)
            if self.auto and self.frames <= AUTO_CHECK_FRAMES:
                # auto-picked points that match elsewhere than the others in most of the first frames are not
                # static: drop them (one frame's mismatch is noise: a streak, a passing shadow)
                self._misses += good & ~agree
                self._checks += good
                if self.frames == AUTO_CHECK_FRAMES:
                    self.usable &= ~(2 * self._misses > self._checks)
            self.ok = agree
        self._settle()
        self.offset = self.raw - self.rest
        return float(self.offset[0]), float(self.offset[1])

    def _settle(self) -> None:
        """Fit the first REST_FRAMES shifts with a line over the frame number and move the applied rest position
        towards its intercept."""
        if self.frames <= REST_FRAMES:
            k = float(self.frames - 1)
            self._n, self._sk, self._skk = self._n + 1.0, self._sk + k, self._skk + k * k
            self._sy, self._sky = self._sy + self.raw, self._sky + k * self.raw
            det = self._n * self._skk - self._sk ** 2
            if self._n >= REST_MIN_FRAMES and det > 0:
                self._target = (self._skk * self._sy - self._sk * self._sky) / det
        if self._target is not None:
            self.rest += np.clip(self._target - self.rest, -REST_STEP_PX, REST_STEP_PX)

    @property
    def n_ok(self) -> int:
        return int(self.ok.sum())

    @property
    def n_total(self) -> int:
        return int(self.usable.sum())
