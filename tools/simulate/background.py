"""The static scene, drawn once: road surface, markings, verges, sky, roadside objects and their shadows."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from tools.simulate.camera import Camera
from tools.simulate.road import RoadLayout
from tools.simulate.vehicles import _Builder

MAP_X = (-32.0, 32.0)
MAP_Y = (-5.0, 420.0)
SX, SY = 24.0, 8.0  # texture map pixels per metre across / along
DASH, GAP = 3.0, 9.0  # lane-line dashes (m)


@dataclass
class StaticObject:
    """A roadside object pre-rendered to an image patch with a mask, drawn in painter's order."""

    name: str
    depth: float  # ground distance from the camera, for painter's ordering
    x0: int
    y0: int
    patch: np.ndarray
    mask: np.ndarray
    parts: np.ndarray  # (P, 8, 3) world corners
    fiducials: list[tuple[float, float]]


def _lowfreq(rng: np.random.Generator, shape: tuple[int, int], cells: tuple[int, int], amp: float) -> np.ndarray:
    small = rng.normal(0.0, amp, size=cells).astype(np.float32)
    return cv2.resize(small, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)


def _road_map(layout: RoadLayout, rng: np.random.Generator, stop_line_y: float | None, wet: bool) -> np.ndarray:
    """Top-down texture of the road plane (float32 grey, rows = Y, cols = X)."""
    h = int((MAP_Y[1] - MAP_Y[0]) * SY)
    w = int((MAP_X[1] - MAP_X[0]) * SX)
    X = MAP_X[0] + (np.arange(w) + 0.5) / SX
    Y = MAP_Y[0] + (np.arange(h) + 0.5) / SY
    img = 78.0 + _lowfreq(rng, (h, w), (160, 24), 14.0) + 13.0 * rng.standard_normal((h, w), dtype=np.float32)
    grass_tufts = _lowfreq(rng, (h, w), (900, 160), 9.0)
    img += grass_tufts
    x_lo, x_hi = layout.x_min - 0.8, layout.x_max + 0.8
    c0, c1 = int((x_lo - MAP_X[0]) * SX), int((x_hi - MAP_X[0]) * SX)
    asphalt = 100.0 + _lowfreq(rng, (h, c1 - c0), (120, 6), 7.0) + 9.0 * rng.standard_normal((h, c1 - c0), dtype=np.float32)
    if wet:
        asphalt = 0.7 * asphalt + 10
    img[:, c0:c1] = asphalt
    # gravel shoulders
    for xs in ((layout.x_min - 2.0, layout.x_min - 0.8), (layout.x_max + 0.8, layout.x_max + 2.0)):
        a, b = int((xs[0] - MAP_X[0]) * SX), int((xs[1] - MAP_X[0]) * SX)
        img[:, a:b] = 125.0 + 16.0 * rng.standard_normal((h, b - a), dtype=np.float32)

    def col(x: float) -> int:
        return int(round((x - MAP_X[0]) * SX))

    def row(y: float) -> int:
        return int(round((y - MAP_Y[0]) * SY))

    # patches and cracks
    for _ in range(120):
        y = rng.uniform(*MAP_Y)
        x = rng.uniform(layout.x_min, layout.x_max)
        w_m, h_m = rng.uniform(0.5, 2.5), rng.uniform(0.5, 4.0)
        r0, c0_ = row(y), col(x)
        patch = img[r0 : row(y + h_m), c0_ : col(x + w_m)]
        patch += float(rng.choice([-1.0, 1.0]) * rng.uniform(3.0, 8.0))
    for _ in range(160):
        pts = [(col(rng.uniform(layout.x_min, layout.x_max)), row(rng.uniform(*MAP_Y)))]
        for _ in range(5):
            pts.append((pts[-1][0] + int(rng.normal(0, 12)), pts[-1][1] + int(rng.normal(0, 8))))
        cv2.polylines(img, [np.array(pts, np.int32)], False, 62.0, 1)
    # tyre tracks
    for ln in layout.lanes:
        for off in (-0.85, 0.85):
            a, b = col(ln.xc + off - 0.3), col(ln.xc + off + 0.3)
            img[:, a:b] -= 7.0
    paint = 205.0 if not wet else 160.0
    # edge lines
    for x in (layout.x_min + 0.1, layout.x_max - 0.1):
        img[:, col(x - 0.1) : col(x + 0.1)] = paint
    # lane lines: dashes between lanes of one direction, double line between directions
    for a, b in zip(layout.lanes[:-1], layout.lanes[1:]):
        x = a.x1
        if a.direction != b.direction:
            for dx in (-0.18, 0.18):
                img[:, col(x + dx - 0.06) : col(x + dx + 0.06)] = paint
        else:
            phase = rng.uniform(0, DASH + GAP)
            y = MAP_Y[0] - phase
            while y < MAP_Y[1]:
                img[max(row(y), 0) : max(row(y + DASH), 0), col(x - 0.075) : col(x + 0.075)] = paint
                y += DASH + GAP
    if stop_line_y is not None:
        appr = [ln for ln in layout.lanes if ln.direction < 0]
        if appr:
            img[row(stop_line_y - 0.4) : row(stop_line_y), col(appr[0].x0) : col(appr[-1].x1)] = paint
    return np.clip(img, 0, 255).astype(np.float32)


def _build_objects(layout: RoadLayout, light: np.ndarray, ambient: float, night: bool,
                   exposure: float) -> list[tuple[str, _Builder]]:
    def B(albedo: float) -> _Builder:
        b = _Builder(+1, light, ambient, night, albedo)
        b.exposure = exposure
        return b

    objs = []
    xl, xr = layout.x_min, layout.x_max
    for k, y in enumerate((28.0, 68.0, 108.0, 148.0)):
        b = B(0.55)
        px = xl - 2.2
        b.box((px - 0.13, px + 0.13, y - 0.13, y + 0.13, 0.0, 9.0))
        b.box((px, xl + 1.8, y - 0.08, y + 0.08, 8.8, 9.0))
        b.box((xl + 1.2, xl + 2.0, y - 0.2, y + 0.2, 8.6, 8.85), albedo=0.3)
        b.decal((xl + 1.2, xl + 2.0, y - 0.2, y + 0.2, 8.6, 8.85), 0, 0.1, 0.9, 0.1, 0.9, 0.9,
                emissive=250.0 if night else None)
        b.decal((px - 0.13, px + 0.13, y - 0.13, y + 0.13, 0.0, 9.0), 2, 0.0, 1.0, 0.1, 0.16, 0.05)
        objs.append((f"lamp{k + 1}", b))
    # cantilever direction sign over the right-most lane
    y = 46.0
    b = B(0.5)
    b.box((xr + 1.1, xr + 1.45, y + 0.1, y + 0.45, 0.0, 7.6))
    panel = (xr - 3.2, xr + 1.1, y, y + 0.15, 5.0, 7.3)
    b.box(panel, albedo=0.12)
    b.decal(panel, 2, 0.03, 0.97, 0.05, 0.95, 0.2)
    b.decal(panel, 2, 0.06, 0.94, 0.1, 0.9, 0.08)
    for r, (c0, c1) in enumerate(((0.12, 0.7), (0.12, 0.55), (0.12, 0.82))):
        b.decal(panel, 2, c0, c1, 0.68 - 0.22 * r, 0.8 - 0.22 * r, 0.95)
    b.decal(panel, 2, 0.78, 0.9, 0.15, 0.42, 0.95)
    objs.append(("sign", b))
    # small ground sign on the left verge
    y = 20.0
    b = B(0.5)
    b.box((xl - 1.6, xl - 1.5, y, y + 0.1, 0.0, 2.4))
    sp = (xl - 2.2, xl - 0.9, y - 0.05, y, 1.5, 2.5)
    b.box(sp, albedo=0.9)
    b.decal(sp, 2, 0.08, 0.92, 0.1, 0.9, 0.1)
    b.decal(sp, 2, 0.2, 0.8, 0.35, 0.65, 0.9)
    objs.append(("ground-sign", b))
    # delineator posts
    for k, y in enumerate(np.arange(15.0, 200.0, 25.0)):
        for side, x in (("L", xl - 1.3), ("R", xr + 1.3)):
            b = B(0.85)
            post = (x - 0.06, x + 0.06, y, y + 0.12, 0.0, 1.1)
            b.box(post)
            b.decal(post, 2, 0.0, 1.0, 0.62, 0.8, 0.05)
            objs.append((f"post{side}{k + 1}", b))
    return objs


def draw_quads(img: np.ndarray, cam: Camera, quads: np.ndarray, normals: np.ndarray, values: np.ndarray,
               shift: int = 4) -> None:
    """Fill the camera-facing quads (in order) with their grey values; subpixel via `shift` bits."""
    if len(quads) == 0:
        return
    px, depth = cam.project(quads)
    centre = quads.mean(axis=1)
    facing = np.einsum("ij,ij->i", normals, centre - cam.centre) < 0
    ok = facing & (depth > 0.5).all(axis=1)
    pts = np.round(px * (1 << shift)).astype(np.int32)
    for i in np.nonzero(ok)[0]:
        cv2.fillConvexPoly(img, pts[i], float(values[i]), cv2.LINE_8, shift)


def shadow_points(corners: np.ndarray, sun: np.ndarray) -> np.ndarray:
    """Project 3D points along the sun direction onto the road plane: (..., 3) -> (..., 2)."""
    k = corners[..., 2:3] / sun[2]
    return corners[..., :2] - k * sun[:2]


def render_background(cam: Camera, layout: RoadLayout, rng: np.random.Generator, *, sun: np.ndarray,
                      ambient: float, shadows: bool, night: bool, exposure: float, wet: bool,
                      stop_line_y: float | None, lamp_ys: list[float]) -> tuple[np.ndarray, np.ndarray, list[StaticObject]]:
    """(background, background in shadow, static objects) at the camera's resolution."""
    ss = 2
    cam2 = cam.scaled(ss)
    tex = _road_map(layout, rng, stop_line_y, wet)
    if night:
        Y = MAP_Y[0] + (np.arange(tex.shape[0]) + 0.5) / SY
        X = MAP_X[0] + (np.arange(tex.shape[1]) + 0.5) / SX
        lit = np.full((len(Y), len(X)), 0.05, np.float32)
        for ly in lamp_ys:
            lx = layout.x_min + 1.6
            lit += 1.1 * np.exp(-((Y[:, None] - ly) ** 2) / (2 * 7.0**2) - ((X[None, :] - lx) ** 2) / (2 * 6.0**2))
        tex = tex * np.minimum(lit, 1.2)
    stex = cv2.GaussianBlur(tex, (0, 0), sigmaX=1.5, sigmaY=5.0)
    if layout.curved:  # the map is drawn in the straight frame: look each pixel up at X - centre_x(Y)
        mx, my = _curved_map_coords(cam2, layout)
        big = cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        soft = cv2.remap(stex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    else:
        A = np.array([[1 / SX, 0, MAP_X[0]], [0, 1 / SY, MAP_Y[0]], [0, 0, 1.0]])
        M = cam2.road_to_image_matrix() @ A
        big = cv2.warpPerspective(tex, M, (cam2.width, cam2.height_px), flags=cv2.INTER_LINEAR,
                                  borderMode=cv2.BORDER_REPLICATE)
        # poor man's mip-mapping: far rows come from a texture blurred along the road, against aliasing streaks
        soft = cv2.warpPerspective(stex, M, (cam2.width, cam2.height_px), flags=cv2.INTER_LINEAR,
                                   borderMode=cv2.BORDER_REPLICATE)
    centre_col = np.full(cam2.height_px, cam2.width / 2.0)
    road_y = cam2.image_to_road(np.column_stack([centre_col, np.arange(cam2.height_px, dtype=np.float64)]))[:, 1]
    road_y = np.where(np.isfinite(road_y) & (road_y > 0), road_y, 1e6)
    wsoft = np.clip((road_y - 50.0) / 70.0, 0.0, 1.0).astype(np.float32)[:, None]
    big = big * (1.0 - wsoft) + soft * wsoft
    big *= exposure
    # sky and a tree line above the horizon
    hz = cam2.horizon_row() + 3 * ss
    rows = np.arange(cam2.height_px, dtype=np.float32)[:, None]
    sky = (150.0 + 60.0 * np.clip((hz - rows) / max(hz, 1.0), 0, 1)) * (0.15 if night else 1.0) * min(exposure * 1.4, 1.0)
    tree_top = hz - (8 + 10 * np.abs(_lowfreq(rng, (1, cam2.width), (1, 40), 1.0)[0])) * ss
    trees = (rows >= tree_top[None, :]) & (rows < hz)
    tree_val = (55.0 + 10.0 * rng.standard_normal((cam2.height_px, cam2.width), dtype=np.float32)) * (0.2 if night else exposure)
    above = rows < hz
    big = np.where(above, np.broadcast_to(sky, big.shape), big)
    big = np.where(trees, tree_val, big).astype(np.float32)
    bg = cv2.resize(big, (cam.width, cam.height_px), interpolation=cv2.INTER_AREA)
    bg_u8 = np.clip(bg, 0, 255).astype(np.uint8)
    bg_shadow = np.clip(bg * (ambient if not night else 1.0), 0, 255).astype(np.uint8)

    objects: list[StaticObject] = []
    shadow_mask = np.zeros_like(bg_u8)
    for name, b in _build_objects(layout, sun, ambient, night, exposure):
        quads = np.array(b.quads)
        parts = np.array(b.parts)
        if layout.curved:  # objects are laid out beside the straight road: move them with the bend
            quads[..., 0] += layout.centre_x(quads[..., 1])
            parts[..., 0] += layout.centre_x(parts[..., 1])
        if shadows:
            for part in parts:
                sp = cam.road_to_image(shadow_points(part, sun))
                hull = cv2.convexHull(np.round(sp * 16).astype(np.int32))
                cv2.fillConvexPoly(shadow_mask, hull, 255, cv2.LINE_8, 4)
        canvas = np.zeros_like(bg_u8)
        draw_quads(canvas, cam, quads, np.array(b.normals), np.array(b.values))
        mask = np.zeros_like(bg_u8)
        draw_quads(mask, cam, quads, np.array(b.normals), np.full(len(quads), 255.0))
        ys, xs = np.nonzero(mask)
        if len(xs) == 0:
            continue
        x0, x1, y0, y1 = xs.min(), xs.max() + 1, ys.min(), ys.max() + 1
        base = parts.reshape(-1, 3)[:, :2].mean(axis=0)
        depth = float(np.hypot(base[0] - cam.x_m, base[1]))
        fid = []
        if name == "sign":  # near the corners of the sign panel's face
            fid = [tuple(cam.project(np.array(p))[0]) for p in _sign_fiducials(parts[1])]
        elif name.startswith("lamp"):  # where the arm leaves the pole
            fid = [tuple(cam.project(parts[0][[4, 5, 6, 7]].mean(axis=0) - [0, 0, 0.1])[0])]
        elif name.startswith("post"):
            fid = [tuple(cam.project(parts[0][[4, 5, 6, 7]].mean(axis=0) - [0, 0, 0.3])[0])]
        objects.append(StaticObject(name, depth, int(x0), int(y0), canvas[y0:y1, x0:x1].copy(),
                                    mask[y0:y1, x0:x1].copy(), parts, fid))
    if shadows:
        cv2.copyTo(bg_shadow, shadow_mask, bg_u8)
    return bg_u8, bg_shadow, objects


def _curved_map_coords(cam: Camera, layout: RoadLayout) -> tuple[np.ndarray, np.ndarray]:
    """Texture-map column/row (float32) of every image pixel's road point, for a curved road."""
    u, v = np.meshgrid(np.arange(cam.width, dtype=np.float64), np.arange(cam.height_px, dtype=np.float64))
    with np.errstate(divide="ignore", invalid="ignore"):
        road = cam.image_to_road(np.column_stack([u.ravel(), v.ravel()]))
    x, y = road[:, 0], road[:, 1]
    bad = ~np.isfinite(y) | (y < MAP_Y[0]) | (y > 1e4)  # at or above the horizon: sky is drawn over it
    y = np.where(bad, MAP_Y[1], y)
    x = np.where(bad, 0.0, x) - layout.centre_x(y)
    mx = ((x - MAP_X[0]) * SX).reshape(u.shape).astype(np.float32)
    my = ((y - MAP_Y[0]) * SY).reshape(u.shape).astype(np.float32)
    return mx, my


def _sign_fiducials(panel: np.ndarray) -> list[np.ndarray]:
    """Points near the high-contrast corners of the sign panel's face."""
    lo, hi = panel.min(axis=0), panel.max(axis=0)
    y = lo[1]
    xs = (lo[0] + 0.1 * (hi[0] - lo[0]), lo[0] + 0.9 * (hi[0] - lo[0]))
    zs = (lo[2] + 0.1 * (hi[2] - lo[2]), lo[2] + 0.9 * (hi[2] - lo[2]))
    return [np.array([x, y, z]) for x in xs for z in zs]
