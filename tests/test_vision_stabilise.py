"""Stabilisation under camera shake: estimated offsets against the simulator's true shake, and the
shake-aligned previous frame the corner detector and the initial-velocity flow use."""

from __future__ import annotations

import cv2
import numpy as np

from appliance.config import parse_site
from appliance.pipeline import VisionPipeline
from appliance.stabilise import Stabiliser
from appliance.zones import SiteZones
from tools.simulate.stream import SceneStream

FRAMES = 150  # 6 s of wind-shake: jitter of ~2.5 px per axis plus 2 px of drift


def _shake_run(enabled: bool, seed: int = 5) -> np.ndarray:
    """Per-frame error (N, 2) of the stabiliser's offset against the true image motion since frame 0."""
    stream = SceneStream("wind-shake", seed)
    site = parse_site(stream.site_dict())
    cond = stream.scene.conditions
    true: list[tuple[float, float]] = []
    offset = cond.offset

    def record(t: float) -> tuple[float, float]:
        d = offset(t)
        true.append(d)
        return d

    cond.offset = record  # the scene asks its conditions for the shake once per rendered frame
    stab = Stabiliser(site.fiducials, SiteZones(site).lane_image, enabled=enabled)
    est = []
    for _ in range(FRAMES):
        img, _ = stream.next_frame()
        est.append(stab.step(img))
    tru = np.array(true[-FRAMES:])
    # the stabiliser's reference is the first frame, which carries its own shake
    return np.array(est) - (tru - tru[0])


def test_offsets_track_true_shake():
    err = np.abs(_shake_run(True))
    # 0.5 px: subpixel NCC on 8 fiducials under 2.5-grey-level noise and defocus; measured ~0.1 px rms,
    # <= 0.3 px max over 8000 frames. A 0.5 px error at 90 m is ~0.5 m of false motion per frame.
    assert err.max() <= 0.5, f"max offset error {err.max(axis=0)} px"
    assert np.sqrt((err**2).mean()) <= 0.2, f"rms offset error {np.sqrt((err**2).mean(axis=0))} px"


def test_disabled_stabiliser_misses_the_shake():
    err = np.abs(_shake_run(False))
    # the check above must be able to fail: without stabilisation the error is the shake itself (σ 2.5 px)
    assert err.max() > 0.5


def test_previous_frame_aligned_to_camera_shift():
    stream = SceneStream("wind-shake", 3)
    pl = VisionPipeline(parse_site(stream.site_dict()))
    base, _ = stream.next_frame()
    d1, d2 = (1.3, -2.6), (-1.7, 0.9)

    def shifted(d: tuple[float, float]) -> np.ndarray:
        M = np.float32([[1, 0, d[0]], [0, 1, d[1]]])
        return cv2.warpAffine(base, M, (pl.width, pl.height), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    prev, cur = shifted(d1), shifted(d2)
    pl.prev, pl.prev_offset, pl.offset = prev, d1, d2
    inner = (slice(20, -20), slice(20, -20))
    raw = cv2.absdiff(cur, prev)[inner]
    aligned = cv2.absdiff(cur, pl._aligned_prev())[inner]
    # a static scene moved by the camera only: aligned, only the smoothing of resampling the noisy
    # (σ 2.5) image twice remains (~1 grey level, < 2); unaligned, every edge differs (~12 on average)
    assert aligned.mean() < 2.0 and raw.mean() > 3.0 * 2.0, (aligned.mean(), raw.mean())
    # the motion mask's level (corners.MOTION_LEVEL) is crossed at far fewer pixels once aligned
    from appliance.corners import MOTION_LEVEL
    assert (aligned > MOTION_LEVEL).mean() < 0.1 * (raw > MOTION_LEVEL).mean()
