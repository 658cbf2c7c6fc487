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


def _shake_run(enabled: bool, seed: int = 5, frames: int = FRAMES) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame (N, 2): the stabiliser's shift from the first frame, its offset from the camera's rest
    position, and the true image motion from the rest position (the simulator's shake and drift)."""
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
    raw, est = [], []
    for _ in range(frames):
        img, _ = stream.next_frame()
        est.append(stab.step(img))
        raw.append(stab.raw.copy())
    return np.array(raw), np.array(est), np.array(true[-frames:])


def test_offsets_track_true_shake():
    raw, _, tru = _shake_run(True)
    # the shift from the first frame, which carries its own shake
    err = np.abs(raw - (tru - tru[0]))
    # 0.5 px: subpixel NCC on 8 fiducials under 2.5-grey-level noise and defocus; measured ~0.1 px rms,
    # <= 0.3 px max over 8000 frames. A 0.5 px error at 90 m is ~0.5 m of false motion per frame.
    assert err.max() <= 0.5, f"max offset error {err.max(axis=0)} px"
    assert np.sqrt((err**2).mean()) <= 0.2, f"rms offset error {np.sqrt((err**2).mean(axis=0))} px"


def test_disabled_stabiliser_misses_the_shake():
    _, est, tru = _shake_run(False)
    err = np.abs(est - (tru - tru[0]))
    # the check above must be able to fail: without stabilisation the error is the shake itself (σ 2.5 px)
    assert err.max() > 0.5


def test_offsets_are_referred_to_the_cameras_rest_position_not_the_first_frame():
    """The site is calibrated at the camera's rest position; the first frame is shaken like any other (seed 8:
    by 2.4 px across and 1.6 px down). Every road position would carry that shift for good, and a shift in
    the image is metres far away (2 px is about 2 m at 80 m: a speed 3 % low over a passage from there).
    Once the stabiliser has seen the camera shake about its rest position (and drift) for a while, its
    offsets are from that rest position."""
    _, est, tru = _shake_run(True, seed=5, frames=500)
    first = np.abs(tru[0])
    assert first.max() > 1.5, f"the first frame's own shake {tru[0]} px: too small to tell"
    late = np.abs((est - tru)[250:]).mean(axis=0)
    # within 0.6 px on average: the intercept of a line through 10-20 s of shake of 2.5 px (about 2 frames
    # correlated) is good to some 0.4 px
    assert late.max() < 0.6 and (late < 0.5 * first + 0.1).all(), (late, tru[0])


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
