"""The empty road as the camera sees it (the median of the first frames, then a running approximate median),
and the test whether an image region is only a shadow on it: darker by one factor, the road's texture still
there."""

from __future__ import annotations

import cv2
import numpy as np
from numba import njit

# It starts as the per-pixel median of WARMUP_SAMPLES frames, one in WARMUP_EVERY from the first (2 s at
# 25 fps: passing vehicles cover a pixel far less than half of that, and the tests answer from then on) ...
WARMUP_SAMPLES = 25
WARMUP_EVERY = 2
UPDATE_EVERY = 4  # ... then follows it: frames between updates (moving vehicles never stay long enough)
# ... but where traffic covers the road much of the time (far away a tall vehicle's body and shadow cover many
# rows; a platoon of trucks passes for seconds) a step each update drags the median 10 grey levels or more off
# the road, which then reads brightened in sunlit places and fails the shadow test. After the first
# FAST_UPDATES, a pixel this many grey levels off the background is something on the road (a vehicle, its
# shadow) and is learnt at one update in FOREGROUND_EVERY only, unless half the frame is that far off (the light
# changed). A lasting change of one place (road works, a parked vehicle) is learnt that much slower while it is
# that far off: 50 levels in about 30 s at 25 fps, against 8 s.
FOREGROUND = 30
FOREGROUND_EVERY = 8
LIGHT_CHANGE_SHARE = 0.5
FAST_UPDATES = 100  # the first updates move this many grey levels at once (what stood through the start) ...
FAST_STEP = 4
# ... and the loops' watches (appliance.presence) start from it only after this many (8 s more at 25 fps): a
# vehicle that stood on a loop through most of the start is learnt into the median, and the empty road it
# leaves would read as one standing there for minutes (a slow truck over a loop in a dense stream will do)
SETTLE_UPDATES = 50
# The frames are learnt as they come, the camera shaking and drifting: the background lines up with the camera's
# offset (the stabiliser's) followed as its grey levels are, by at most OFFSET_STEP_PX an update (1.5 px/s)
OFFSET_STEP_PX = 0.25
NOISE = 10  # grey levels: a pixel this close to the background is the road as usual
PAD_PX = 3
MAX_BRIGHT_SHARE = 0.08  # a shadow brightens nothing (a little of its bright caster may be in the box)
MIN_DARK_SHARE = 0.15
SHADOW_RATIO = (0.2, 0.85)  # shadow over sunlit road: the share of light the sky still gives
# A shadow dims the road by one factor: most darkened pixels (its core; the rest are its penumbra and the
# caster's edge) are within CORE_TOL of the median ratio; a vehicle's own pattern spreads the ratios.
CORE_TOL = 0.1
MIN_CORE_SHARE = 0.65
MIN_TEXTURE = 6.0  # grey-level std of the road under the core: below it noise swamps the texture test ...
FLAT_CORE_SHARE = 0.85  # ... and the road, too plain to tell, must be dimmed this evenly instead
MIN_TEXTURE_NCC = 0.5  # the shadowed road still correlates with the road (a dark vehicle does not)
CELL_PX = 6  # ... compared in cells of this size, those this dark (inside the shadow) ...
CELL_DARK_SHARE = 0.9
MIN_CELLS = 3  # ... when the box holds this many textured ones
MIN_CELL_SHARE = 0.6  # ... of which this share must correlate
MIN_INNER_PX = 12  # else over the dark area without its edge pixels (when this many are left)
# A few points (a thin shadow's tip, a low sun's: its box is mostly road and penumbra) are judged on a box
# reaching TOWARD_PX further towards the caster too, along the shadow's body
TOWARD_MAX_POINTS = 3
TOWARD_PX = 18
MIN_ATTACHED_DARK = 0.6  # the image between a vehicle and its shadow is shadow too (a shadow touches its caster)
MIN_JOINED_SHARE = 0.85  # the image between two parts of one vehicle is that vehicle, not the road


class Background:
    """Approximate median (McFarlane & Schofield): each update moves every pixel a step towards the frame (a
    pixel far off it, at one update in FOREGROUND_EVERY)."""

    def __init__(self) -> None:
        self.bg: np.ndarray | None = None
        self.frames = 0
        self.updates = 0
        self.samples: np.ndarray | None = None  # the start's frames (WARMUP_SAMPLES), until their median is taken ...
        self.offsets = np.zeros((0, 2))  # ... the camera's offsets then ...
        self.n_samples = 0  # ... and how many are in
        self.offset = np.zeros(2)  # the camera's offset the background lines up with (see OFFSET_STEP_PX)
        self.now = (0.0, 0.0)  # the camera's offset in the frame last learnt ...
        self._view: np.ndarray | None = None  # ... and the background moved to line up with it (see aligned)

    def update(self, img: np.ndarray, offset: tuple[float, float] = (0.0, 0.0)) -> None:
        """Learn frame img, taken at the camera's offset (the stabiliser's)."""
        self.now, self._view = offset, None
        if self.bg is not None and self.bg.shape != img.shape:
            self.bg = None
        if self.bg is None:
            if self.samples is None or self.samples.shape[1:] != img.shape:
                self.samples = np.empty((WARMUP_SAMPLES, *img.shape), np.uint8)
                self.offsets = np.empty((WARMUP_SAMPLES, 2))
                self.n_samples = self.frames = 0
            if self.frames % WARMUP_EVERY == 0:
                self.samples[self.n_samples] = img
                self.offsets[self.n_samples] = offset
                self.n_samples += 1
            self.frames += 1
            if self.n_samples == len(self.samples):
                self.bg = np.empty_like(img)
                temporal_median(self.samples, self.bg)
                self.offset = np.median(self.offsets, axis=0)
                self.samples, self.frames, self.updates = None, 0, 0
            return
        self.frames += 1
        if self.frames % UPDATE_EVERY:
            return
        self.offset += np.clip(np.asarray(offset, np.float64) - self.offset, -OFFSET_STEP_PX, OFFSET_STEP_PX)
        step = FAST_STEP if self.updates < FAST_UPDATES else 1
        road = None
        if self.updates >= FAST_UPDATES and self.updates % FOREGROUND_EVERY:
            road = cv2.compare(cv2.absdiff(img, self.bg), FOREGROUND, cv2.CMP_LE)
            if cv2.countNonZero(road) < (1.0 - LIGHT_CHANGE_SHARE) * road.size:
                road = None
        for op, cmp in ((cv2.add, cv2.CMP_GT), (cv2.subtract, cv2.CMP_LT)):
            # (one after the other: a fast step that overshot the frame is taken back within the update)
            mask = cv2.compare(img, self.bg, cmp)
            op(self.bg, step, dst=self.bg, mask=mask if road is None else cv2.bitwise_and(mask, road))
        self.updates += 1

    @property
    def ready(self) -> bool:
        return self.bg is not None

    @property
    def settled(self) -> bool:
        return self.bg is not None and self.updates >= SETTLE_UPDATES

    @property
    def aligned(self) -> np.ndarray:
        """The background moved by whole pixels to line up with the frame last learnt (a shaking camera's frame
        lies pixels away from it): what the image tests compare that frame with."""
        if self._view is None:
            dx, dy = (int(round(self.now[k] - self.offset[k])) for k in (0, 1))
            if dx == 0 and dy == 0:
                self._view = self.bg
            else:
                h, w = self.bg.shape
                self._view = cv2.warpAffine(self.bg, np.float32([[1, 0, dx], [0, 1, dy]]), (w, h),
                                            borderMode=cv2.BORDER_REPLICATE)
        return self._view

    def is_attached_shadow(self, img: np.ndarray, pts: np.ndarray, caster: np.ndarray) -> bool:
        """True when the points pts are on a shadow that reaches the caster's points in the image: the
        road between the two, across the rows they share, is shadowed too (two vehicles side by side
        have sunlit road between them)."""
        if len(caster) == 0:
            return False
        if not self.is_shadow(img, pts):
            box = _toward(pts, caster) if len(pts) <= TOWARD_MAX_POINTS else None
            if box is None or not self.is_shadow(img, box):
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
        b = self.aligned[r0:r1, c0:c1].astype(np.int16)
        n = a.size
        return (np.count_nonzero(a > b + NOISE) <= MAX_BRIGHT_SHARE * n
                and np.count_nonzero(a < b - NOISE) >= MIN_ATTACHED_DARK * n)

    def is_joined(self, img: np.ndarray, pts: np.ndarray, other: np.ndarray, share: float | None = None) -> bool:
        """True when the image along the line between the nearest two of points pts and other differs from
        the road (in MIN_JOINED_SHARE of its pixels, or share): the two are parts of one body (two vehicles have
        road between them)."""
        if not self.ready or len(pts) == 0 or len(other) == 0:
            return False
        d = ((pts[:, None, :] - other[None, :, :]) ** 2).sum(axis=2)
        i, j = np.unravel_index(int(np.argmin(d)), d.shape)
        a, b = pts[i], other[j]
        n = int(np.abs(b - a).max()) + 1
        h, w = img.shape
        xs = np.clip(np.round(np.linspace(a[0], b[0], n)).astype(np.int64), 0, w - 1)
        ys = np.clip(np.round(np.linspace(a[1], b[1], n)).astype(np.int64), 0, h - 1)
        diff = np.abs(img[ys, xs].astype(np.int16) - self.aligned[ys, xs].astype(np.int16))
        return np.count_nonzero(diff > NOISE) >= (MIN_JOINED_SHARE if share is None else share) * n

    def is_shadow(self, img: np.ndarray, pts: np.ndarray, plain_ok: bool = True) -> bool:
        """True when the box around image points pts (n x 2, x y) differs from the road only by a shadow.
        Where the road is too plain for the texture test, an evenly dimmed box counts if plain_ok."""
        if not self.ready or len(pts) == 0:
            return False
        return bool(shadow_at(img, self.aligned, np.asarray(pts, np.float64), plain_ok))


def _toward(pts: np.ndarray, caster: np.ndarray) -> np.ndarray | None:
    """pts and two points TOWARD_PX beyond them towards the caster, on their top and bottom rows (not past the
    caster), for the shadow test's box (see TOWARD_MAX_POINTS); None where the two overlap across the image."""
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    if caster[:, 0].max() < lo[0]:
        x = max(lo[0] - TOWARD_PX, float(caster[:, 0].max()))
    elif caster[:, 0].min() > hi[0]:
        x = min(hi[0] + TOWARD_PX, float(caster[:, 0].min()))
    else:
        return None
    return np.vstack([pts, [[x, lo[1]], [x, hi[1]]]])


@njit(cache=True)
def temporal_median(stack: np.ndarray, out: np.ndarray) -> None:
    """Per pixel, the median (the upper of the middle two for an even count) of the grey levels of the frames
    stack (n, h, w), into out (h, w): by a histogram, a fifth of np.median's time."""
    n, h, w = stack.shape
    hist = np.zeros(256, np.int32)
    half = n // 2
    for y in range(h):
        for x in range(w):
            for k in range(n):
                hist[stack[k, y, x]] += 1
            c = 0
            for g in range(256):
                c += hist[g]
                if c > half:
                    out[y, x] = g
                    break
            for k in range(n):
                hist[stack[k, y, x]] = 0


@njit(cache=True)
def shadow_at(img: np.ndarray, bg: np.ndarray, pts: np.ndarray, plain_ok: bool) -> bool:
    """shadow_box on the box around image points pts (n x 2, x y), PAD_PX wider, within the image; False for
    a box narrower than 3 pixels."""
    h, w = img.shape
    x0, y0 = int(np.floor(pts[:, 0].min())) - PAD_PX, int(np.floor(pts[:, 1].min())) - PAD_PX
    x1, y1 = int(np.ceil(pts[:, 0].max())) + PAD_PX + 1, int(np.ceil(pts[:, 1].max())) + PAD_PX + 1
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
    if x1 - x0 < 3 or y1 - y0 < 3:
        return False
    return shadow_box(img[y0:y1, x0:x1], bg[y0:y1, x0:x1], plain_ok)


@njit(cache=True)
def shadow_box(img: np.ndarray, bg: np.ndarray, plain_ok: bool) -> bool:  # noqa: C901
    """Background.is_shadow's test on one box (the image's and the road's pixels): brightened nowhere, dimmed
    by one factor (the median ratio of its dark pixels), the road's texture seen through the dimmed part, cell
    by cell where there are MIN_CELLS textured dark cells, else over the dark area away from its edges (a plain
    road: an even dimming, if plain_ok). Reference: appliance.kernels_ref.shadow_box_ref."""
    h, w = img.shape
    n = h * w
    a = img.astype(np.float32)
    b = bg.astype(np.float32)
    bright = 0
    dark = np.zeros((h, w), np.bool_)
    nd = 0
    for y in range(h):
        for x in range(w):
            if a[y, x] > b[y, x] + NOISE:
                bright += 1
            elif a[y, x] < b[y, x] - NOISE:
                dark[y, x] = True
                nd += 1
    if bright > MAX_BRIGHT_SHARE * n or nd < MIN_DARK_SHARE * n:
        return False
    rr = np.empty(nd, np.float32)
    k = 0
    for y in range(h):
        for x in range(w):
            if dark[y, x]:
                rr[k] = a[y, x] / max(b[y, x], np.float32(1.0))
                k += 1
    m = nd // 2
    part = np.partition(rr, m)  # the median as NumPy's: the middle value, or the mean of the two
    ratio = part[m] if nd % 2 else np.float32((part[:m].max() + part[m]) / np.float32(2.0))
    if not SHADOW_RATIO[0] <= ratio <= SHADOW_RATIO[1]:
        return False
    core = 0
    for i in range(nd):
        if abs(rr[i] - ratio) <= np.float32(CORE_TOL):
            core += 1
    if core < MIN_CORE_SHARE * nd:
        return False
    # The road's texture is compared cell by cell inside the dark area: a vehicle next to its own shadow
    # would pass a test over the whole box (the shadow's part correlates), its body's cells do not.
    c = CELL_PX
    nc = good = 0
    for cy in range(h // c):
        for cx in range(w // c):
            sd = 0
            for y in range(cy * c, cy * c + c):
                for x in range(cx * c, cx * c + c):
                    sd += dark[y, x]
            if sd / (c * c) < CELL_DARK_SHARE:
                continue  # a cell of the shadow's edge, or of its caster
            sa = sb = 0.0
            for y in range(cy * c, cy * c + c):
                for x in range(cx * c, cx * c + c):
                    sa += a[y, x]
                    sb += b[y, x]
            ma, mb = sa / (c * c), sb / (c * c)
            vaa = vbb = vab = 0.0
            for y in range(cy * c, cy * c + c):
                for x in range(cx * c, cx * c + c):
                    da, db = a[y, x] - ma, b[y, x] - mb
                    vaa += da * da
                    vbb += db * db
                    vab += da * db
            sda, sdb = np.sqrt(vaa / (c * c)), np.sqrt(vbb / (c * c))
            if sdb >= MIN_TEXTURE:
                nc += 1
                if vab / (c * c) / max(sda * sdb, 1e-6) >= MIN_TEXTURE_NCC:
                    good += 1
    if nc >= MIN_CELLS:
        return good >= MIN_CELL_SHARE * nc
    # too small for cells: the whole dark area away from its edges (penumbra, the caster's outline); the box's
    # border erodes nothing (as cv2.erode's default border)
    inner = np.zeros((h, w), np.bool_)
    ni = 0
    for y in range(h):
        for x in range(w):
            if not dark[y, x]:
                continue
            keep = True
            for yy in range(max(y - 1, 0), min(y + 2, h)):
                for xx in range(max(x - 1, 0), min(x + 2, w)):
                    if not dark[yy, xx]:
                        keep = False
            inner[y, x] = keep
            ni += keep
    if ni < MIN_INNER_PX:
        inner = dark
        ni = nd
    sa = sb = 0.0
    for y in range(h):
        for x in range(w):
            if inner[y, x]:
                sa += a[y, x]
                sb += b[y, x]
    ma, mb = sa / ni, sb / ni
    vaa = vbb = vab = 0.0
    flat = 0
    for y in range(h):
        for x in range(w):
            if inner[y, x]:
                da, db = a[y, x] - ma, b[y, x] - mb
                vaa += da * da
                vbb += db * db
                vab += da * db
                if abs(a[y, x] / max(b[y, x], np.float32(1.0)) - ratio) <= np.float32(CORE_TOL):
                    flat += 1
    sda, sdb = np.sqrt(vaa / ni), np.sqrt(vbb / ni)
    if sdb < MIN_TEXTURE:
        return plain_ok and flat >= FLAT_CORE_SHARE * ni
    if sda < 1e-3:
        return False
    return vab / ni / (sda * sdb) >= MIN_TEXTURE_NCC
