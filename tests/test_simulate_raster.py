"""The simulator's numba quad filler against its NumPy reference, and against OpenCV's polygon fill."""

from __future__ import annotations

import cv2
import numpy as np

from tools.simulate.raster import fill_quads, fill_quads_ref


def _random_convex_quads(rng: np.random.Generator, n: int) -> np.ndarray:
    centre = rng.uniform(-40, 680, (n, 1, 2))
    ang = np.sort(rng.uniform(0, 2 * np.pi, (n, 4)), axis=1)
    r = rng.uniform(0.3, 50.0, (n, 1, 1))  # one radius per quad: vertices on a circle, so convex
    q = centre + r * np.stack([np.cos(ang), np.sin(ang)], axis=-1)
    q[: n // 10, :, 1] = np.round(q[: n // 10, :, 1])  # some edges exactly on pixel rows
    return q


def test_numba_fill_equals_numpy_reference() -> None:
    rng = np.random.default_rng(1)
    q = _random_convex_quads(rng, 400)
    vals = rng.uniform(-10, 270, len(q))  # out-of-range values clamp to 0..255
    sel = rng.permutation(len(q))[:300]  # painter's order is the order of sel
    a = np.zeros((480, 640), np.uint8)
    b = a.copy()
    fill_quads(a, q, vals, sel)
    fill_quads_ref(b, q, vals, sel)
    assert a.any()
    assert np.array_equal(a, b)


def test_fill_agrees_with_opencv_within_a_pixel_edge() -> None:
    rng = np.random.default_rng(2)
    q = _random_convex_quads(rng, 60)
    q[:, :, 0] = np.clip(q[:, :, 0], 5, 630)
    q[:, :, 1] = np.clip(q[:, :, 1], 5, 470)
    for quad in q:
        mine = np.zeros((480, 640), np.uint8)
        fill_quads(mine, quad[None], np.array([255.0]), np.array([0]))
        ref = np.zeros_like(mine)
        cv2.fillConvexPoly(ref, np.round(quad * 16).astype(np.int32), 255, cv2.LINE_8, 4)
        # the two coverage rules differ only along the outline: every disagreeing pixel touches the other's edge
        diff = mine != ref
        near_edge = cv2.dilate(cv2.Canny(ref, 1, 1), np.ones((3, 3), np.uint8)) > 0
        near_edge |= cv2.dilate(ref, np.ones((3, 3), np.uint8)) != cv2.erode(ref, np.ones((3, 3), np.uint8))
        assert not (diff & ~near_edge).any()
