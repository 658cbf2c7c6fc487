"""The empty road as the camera sees it (a running approximate median of the frames), and the test
whether an image region is only a shadow on it: darker by one factor, the road's texture still there."""

from __future__ import annotations

import cv2
import numpy as np

UPDATE_EVERY = 4  # frames between background updates (moving vehicles never stay long enough to be learnt)
FAST_UPDATES = 100  # the first updates move this many grey levels at once (a quick start) ...
FAST_STEP = 4
READY_UPDATES = 50  # ... and the test answers only after this many updates (8 s at 25 fps)
NOISE = 10  # grey levels: a pixel this close to the background is the road as usual
PAD_PX = 3
MAX_BRIGHT_SHARE = 0.03  # a shadow brightens nothing
MIN_DARK_SHARE = 0.15
SHADOW_RATIO = (0.2, 0.85)  # shadow over sunlit road: the share of light the sky still gives
MIN_TEXTURE = 4.0  # grey-level std of the road under the shadow: below it the texture test cannot tell
MIN_TEXTURE_NCC = 0.4  # the shadowed road still correlates with the road (a dark vehicle does not)
MIN_ATTACHED_DARK = 0.6  # the image between a vehicle and its shadow is shadow too (a shadow touches its caster)


class Background:
    """Approximate median (McFarlane & Schofield): each update moves every pixel a step towards the frame."""

    def __init__(self) -> None:
        self.bg: np.ndarray | None = None
        self.frames = 0
        self.updates = 0

    def update(self, img: np.ndarray) -> None:
        self.frames += 1
        if self.bg is None or self.bg.shape != img.shape:
            self.bg, self.updates = img.copy(), 0
            return
        if self.frames % UPDATE_EVERY:
            return
        step = FAST_STEP if self.updates < FAST_UPDATES else 1
        cv2.add(self.bg, step, dst=self.bg, mask=cv2.compare(img, self.bg, cv2.CMP_GT))
        cv2.subtract(self.bg, step, dst=self.bg, mask=cv2.compare(img, self.bg, cv2.CMP_LT))
        self.updates += 1

    @property
    def ready(self) -> bool:
        return self.bg is not None and self.updates >= READY_UPDATES

    def is_attached_shadow(self, img: np.ndarray, pts: np.ndarray, caster: np.ndarray) -> bool:
        """True when the points pts are on a shadow that reaches the caster's points in the image: the
        road between the two, across the rows they share, is shadowed too (two vehicles side by side
        have sunlit road between them)."""
        if len(caster) == 0 or not self.is_shadow(img, pts):
            return False
        r0 = int(max(pts[:, 1].min(), caster[:, 1].min()))
        r1 = int(np.ceil(min(pts[:, 1].max(), caster[:, 1].max()))) + 1
        if r1 - r0 < 1:
            r0 = int(pts[:, 1].mean())
            r1 = r0 + 1
        if pts[:, 0].min() > caster[:, 0].max():
            c0, c1 = int(np.ceil(caster[:, 0].max())), int(pts[:, 0].min())
        elif pts[:, 0].max() < caster[:, 0].min():
            c0, c1 = int(np.ceil(pts[:, 0].max())), int(caster[:, 0].min())
        else:
            return True  # they overlap across the image
        h, w = img.shape
        r0, r1, c0, c1 = max(r0, 0), min(r1, h), max(c0, 0), min(c1, w)
        if c1 <= c0 or r1 <= r0:
            return True
        a = img[r0:r1, c0:c1].astype(np.int16)
        b = self.bg[r0:r1, c0:c1].astype(np.int16)
        n = a.size
        return (np.count_nonzero(a > b + NOISE) <= MAX_BRIGHT_SHARE * n
                and np.count_nonzero(a < b - NOISE) >= MIN_ATTACHED_DARK * n)

    def is_shadow(self, img: np.ndarray, pts: np.ndarray) -> bool:
        """True when the box around image points pts (n x 2, x y) differs from the road only by a shadow."""
        if not self.ready or len(pts) == 0:
            return False
        h, w = img.shape
        x0, y0 = np.floor(pts.min(axis=0)).astype(int) - PAD_PX
        x1, y1 = np.ceil(pts.max(axis=0)).astype(int) + PAD_PX + 1
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
        if x1 - x0 < 3 or y1 - y0 < 3:
            return False
        a = img[y0:y1, x0:x1].astype(np.float32)
        b = self.bg[y0:y1, x0:x1].astype(np.float32)
        n = a.size
        if np.count_nonzero(a > b + NOISE) > MAX_BRIGHT_SHARE * n:
            return False
        dark = a < b - NOISE
        if np.count_nonzero(dark) < MIN_DARK_SHARE * n:
            return False
        ad, bd = a[dark], b[dark]
        ratio = float(np.median(ad / np.maximum(bd, 1.0)))
        if not SHADOW_RATIO[0] <= ratio <= SHADOW_RATIO[1]:
            return False
        sb, sa = float(bd.std()), float(ad.std())
        if sb < MIN_TEXTURE or sa < 1e-3:
            return False
        ncc = float(np.mean((ad - ad.mean()) * (bd - bd.mean()))) / (sa * sb)
        return ncc >= MIN_TEXTURE_NCC
