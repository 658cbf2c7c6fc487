"""Filling many convex quads in painter's order in one call (numba), with its NumPy reference."""

# A pixel (x, y) is filled when its centre, the integer point (x, y), lies inside the quad (edges included).

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def fill_quads(img: np.ndarray, quads: np.ndarray, vals: np.ndarray, sel: np.ndarray) -> None:
    """Fill quads[sel[i]] (convex, (4, 2) pixel coordinates) with vals[sel[i]], in the order of sel."""
    H, W = img.shape
    for k in range(sel.shape[0]):
        qi = sel[k]
        q = quads[qi]
        v = vals[qi]
        vv = 0 if v < 0 else (255 if v > 255 else int(v + 0.5))
        ylo = min(min(q[0, 1], q[1, 1]), min(q[2, 1], q[3, 1]))
        yhi = max(max(q[0, 1], q[1, 1]), max(q[2, 1], q[3, 1]))
        y0 = max(0, int(math.ceil(ylo)))
        y1 = min(H - 1, int(math.floor(yhi)))
        for y in range(y0, y1 + 1):
            xl = np.inf
            xr = -np.inf
            for e in range(4):
                ax, ay = q[e, 0], q[e, 1]
                bx, by = q[(e + 1) % 4, 0], q[(e + 1) % 4, 1]
                if (ay <= y <= by) or (by <= y <= ay):
                    if ay == by:
                        lo, hi = min(ax, bx), max(ax, bx)
                    else:
                        lo = ax + (y - ay) * (bx - ax) / (by - ay)
                        hi = lo
                    xl = min(xl, lo)
                    xr = max(xr, hi)
            if xl > xr:
                continue
            xa = max(0, int(math.ceil(xl)))
            xb = min(W - 1, int(math.floor(xr)))
            for x in range(xa, xb + 1):
                img[y, x] = vv


def fill_quads_ref(img: np.ndarray, quads: np.ndarray, vals: np.ndarray, sel: np.ndarray) -> None:
    """Plain NumPy version of fill_quads (same coverage rule and rounding), for tests."""
    H, W = img.shape
    for qi in sel:
        q = quads[qi]
        vv = int(np.clip(np.floor(vals[qi] + 0.5), 0, 255))
        y0 = max(0, int(np.ceil(q[:, 1].min())))
        y1 = min(H - 1, int(np.floor(q[:, 1].max())))
        if y1 < y0:
            continue
        ys = np.arange(y0, y1 + 1, dtype=np.float64)[:, None]
        a, b = q, np.roll(q, -1, axis=0)
        ax, ay, bx, by = a[:, 0][None], a[:, 1][None], b[:, 0][None], b[:, 1][None]
        hit = ((ay <= ys) & (ys <= by)) | ((by <= ys) & (ys <= ay))
        flat = ay == by
        with np.errstate(divide="ignore", invalid="ignore"):
            xs = np.where(flat, 0.0, ax + (ys - ay) * (bx - ax) / np.where(flat, 1.0, by - ay))
        lo = np.where(flat, np.minimum(ax, bx), xs)
        hi = np.where(flat, np.maximum(ax, bx), xs)
        xl = np.where(hit, lo, np.inf).min(axis=1)
        xr = np.where(hit, hi, -np.inf).max(axis=1)
        xs_grid = np.arange(W, dtype=np.float64)[None, :]
        inside = (xs_grid >= np.maximum(np.ceil(xl), 0)[:, None]) & (xs_grid <= np.floor(xr)[:, None]) & (xl <= xr)[:, None]
        rows = img[y0 : y1 + 1]
        rows[inside] = vv
