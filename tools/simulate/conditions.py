"""Per-frame imaging conditions applied after drawing: glare, rain, shake/drift, blur, gain, noise, JPEG."""

from __future__ import annotations

import math

import cv2
import numpy as np

from tools.simulate.presets import SceneParams


# motion blur of a camera shaking in wind, per axis: as strong as a 2-px box (variance 0.25 px^2), but
# centred (an even-sized box moves the image half a pixel)
SHAKE_BLUR = np.array([0.125, 0.75, 0.125], np.float32)


def _glare_sprite(radius: int) -> np.ndarray:
    r = np.arange(-2 * radius, 2 * radius + 1, dtype=np.float32)
    d2 = r[:, None] ** 2 + r[None, :] ** 2
    return np.clip(255.0 * np.exp(-d2 / (2.0 * (radius * 0.7) ** 2)), 0, 255).astype(np.uint8)


class Conditions:
    """Holds the precomputed layers (noise, rain) and the slow state (gain, drift) of one scene."""

    def __init__(self, p: SceneParams, width: int, height: int, rng: np.random.Generator):
        self.p, self.w, self.h, self.rng = p, width, height, rng
        # a tall bank of sensor noise; each frame takes a random window of it (no per-frame allocation)
        n = (p.noise_sigma * rng.standard_normal((3 * height, width), dtype=np.float32))
        self.noise_pos = np.clip(n, 0, 255).astype(np.uint8)
        self.noise_neg = np.clip(-n, 0, 255).astype(np.uint8)
        self.rain = []
        if p.rain:
            for _ in range(5):
                layer = np.zeros((height, width), np.uint8)
                for _ in range(int(width * height / 900)):
                    x, y = rng.integers(0, width), rng.integers(0, height)
                    ln = int(rng.integers(6, 22))
                    cv2.line(layer, (int(x), int(y)), (int(x + ln * 0.25), int(y + ln)), int(rng.integers(25, 70)), 1)
                self.rain.append(cv2.blur(layer, (1, 3)))
        self.sprites = {r: _glare_sprite(r) for r in (2, 4, 7, 11)}
        self.gain_ema: float | None = None
        self.drift_dir = rng.uniform(0, 2 * math.pi)
        self.shake_state = np.zeros(2)
        self.frame = 0
        self.night_factor = 1.0 if p.night else 0.0  # set per frame by a day-to-night scene

    def drift(self, t: float) -> tuple[float, float]:
        """Slow camera drift at time t (px), e.g. a pole bending in the sun or a loose mount."""
        d = self.p.drift_px_per_min * t / 60.0
        return d * math.cos(self.drift_dir), d * math.sin(self.drift_dir)

    def offset(self, t: float) -> tuple[float, float]:
        """Camera image motion at time t (px): slow drift plus smoothed wind jitter (advances the jitter)."""
        p = self.p
        dx, dy = self.drift(t)
        if p.shake_px > 0:
            self.shake_state = 0.6 * self.shake_state + 0.8 * self.rng.normal(0.0, p.shake_px, 2)
            dx += float(self.shake_state[0])
            dy += float(self.shake_state[1])
        return dx, dy

    def glare(self, img: np.ndarray, points: np.ndarray, sizes: np.ndarray) -> None:
        """Add glare blobs (headlights) centred on image points with radii `sizes` (px)."""
        for (x, y), s in zip(points, sizes):
            r = min(self.sprites, key=lambda k: abs(k - s))
            sp = self.sprites[r]
            x0, y0 = int(round(x)) - 2 * r, int(round(y)) - 2 * r
            x1, y1 = x0 + sp.shape[1], y0 + sp.shape[0]
            cx0, cy0, cx1, cy1 = max(x0, 0), max(y0, 0), min(x1, self.w), min(y1, self.h)
            if cx0 >= cx1 or cy0 >= cy1:
                continue
            roi = img[cy0:cy1, cx0:cx1]
            cv2.add(roi, sp[cy0 - y0 : cy1 - y0, cx0 - x0 : cx1 - x0], dst=roi)

    def apply(self, img: np.ndarray, t: float, dxy: tuple[float, float]) -> np.ndarray:
        p = self.p
        self.frame += 1
        if p.rain:
            img = cv2.convertScaleAbs(img, alpha=0.72, beta=30)
            cv2.add(img, self.rain[self.frame % len(self.rain)], dst=img)
        if dxy != (0.0, 0.0):
            M = np.float32([[1, 0, dxy[0]], [0, 1, dxy[1]]])
            img = cv2.warpAffine(img, M, (self.w, self.h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        if p.defocus > 0:
            img = cv2.GaussianBlur(img, (0, 0), p.defocus)
        if p.motion_blur and (p.night or p.dusk or self.night_factor > 0.5):
            img = cv2.blur(img, (1, 3))  # long exposure: vehicles smear along their (mostly vertical) image motion
        elif p.motion_blur and p.shake_px > 0:
            img = cv2.sepFilter2D(img, -1, SHAKE_BLUR, SHAKE_BLUR)
        if p.auto_gain:
            m = float(cv2.mean(img[self.h // 3 :: 4, ::4])[0])
            self.gain_ema = m if self.gain_ema is None else 0.97 * self.gain_ema + 0.03 * m
            f = self.night_factor
            target = 55.0 if p.dusk else 105.0 * (1.0 - f) + 50.0 * f
            top = 1.3 if p.dusk else 1.2 + 0.4 * f
            g = float(np.clip(target / max(self.gain_ema, 1.0), 0.85, top))
            if abs(g - 1.0) > 0.01:
                img = cv2.convertScaleAbs(img, alpha=g, beta=0)
        if p.noise_sigma > 0:
            a, b = (int(v) for v in self.rng.integers(0, 2 * self.h, 2))
            img = cv2.subtract(cv2.add(img, self.noise_pos[a : a + self.h]), self.noise_neg[b : b + self.h])
        if p.jpeg_quality > 0:
            ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(p.jpeg_quality)])
            img = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
        return img
