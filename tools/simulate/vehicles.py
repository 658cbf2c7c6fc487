"""Vehicle classes and their 3D box geometry: parts (body, cabin, cab, trailer) and face decals."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# class -> (length range, width range, height range) in metres
CLASS_DIMS: dict[str, tuple[tuple[float, float], tuple[float, float], tuple[float, float]]] = {
    "motorcycle": ((1.9, 2.3), (0.7, 0.9), (1.3, 1.6)),
    "car": ((3.7, 4.9), (1.68, 1.9), (1.38, 1.55)),
    "van": ((4.8, 6.2), (1.9, 2.05), (1.9, 2.6)),
    "truck": ((7.0, 11.0), (2.4, 2.55), (3.0, 3.8)),
    "artic": ((15.0, 18.5), (2.5, 2.55), (3.8, 4.0)),
    "bus": ((10.5, 13.0), (2.5, 2.55), (3.0, 3.3)),
}
# IDM character per class: (max accel m/s^2, comfortable decel m/s^2, desired speed factor)
CLASS_IDM: dict[str, tuple[float, float, float]] = {
    "motorcycle": (2.0, 2.5, 1.05),
    "car": (1.4, 2.0, 1.0),
    "van": (1.2, 2.0, 0.95),
    "truck": (0.8, 1.6, 0.85),
    "artic": (0.6, 1.5, 0.82),
    "bus": (0.8, 1.6, 0.85),
}
# paint albedo choices (grey world): white, silver, grey, dark grey, black, red, blue, road-like (low contrast)
ALBEDOS = np.array([0.85, 0.66, 0.48, 0.26, 0.09, 0.36, 0.22, 0.40])
ALBEDO_P = np.array([0.22, 0.18, 0.14, 0.1, 0.14, 0.08, 0.08, 0.06])

# face index: 0 top, 1 front, 2 rear, 3 left, 4 right
FACES = ("top", "front", "rear", "left", "right")


@dataclass
class Shape:
    """Vehicle geometry in local coordinates (x across, dy along the road from the front point, z up)."""

    quads: np.ndarray  # (Q, 4, 3) local corners; Y offset already signed by direction
    normals: np.ndarray  # (Q, 3) world-oriented normals
    values: np.ndarray  # (Q,) grey value 0..255
    face_of: np.ndarray  # (Q,) part index of each quad
    corners: np.ndarray  # (P*8, 3) all part corners, for bounding boxes and shadows
    parts: np.ndarray  # (P, 8, 3) part corners
    lights: np.ndarray  # (L, 3) light centres (front = head, rear = tail) in local coordinates
    light_front: np.ndarray  # (L,) bool
    length: float
    width: float
    height: float
    decal: np.ndarray | None = None  # (Q,) True for windows, lights and other details on a face
    lamp: np.ndarray | None = None  # (Q,) grey value of a head/tail light when lit, 0 for other quads


def _box(x0, x1, u0, u1, z0, z1) -> np.ndarray:
    """8 corners of a box in (x, u, z)."""
    return np.array([[x, u, z] for z in (z0, z1) for u in (u0, u1) for x in (x0, x1)], dtype=np.float64)


def _face_quad(b: tuple, face: int, a0=0.0, a1=1.0, c0=0.0, c1=1.0) -> np.ndarray:
    """Quad on a face of box b=(x0,x1,u0,u1,z0,z1); (a, c) are fractions across and up the face."""
    x0, x1, u0, u1, z0, z1 = b
    lx = lambda a: x0 + a * (x1 - x0)  # noqa: E731
    lu = lambda a: u0 + a * (u1 - u0)  # noqa: E731
    lz = lambda c: z0 + c * (z1 - z0)  # noqa: E731
    if face == 0:  # top: a across x, c along u
        pts = [(lx(a0), lu(c0), z1), (lx(a1), lu(c0), z1), (lx(a1), lu(c1), z1), (lx(a0), lu(c1), z1)]
    elif face in (1, 2):
        u = u1 if face == 1 else u0
        pts = [(lx(a0), u, lz(c0)), (lx(a1), u, lz(c0)), (lx(a1), u, lz(c1)), (lx(a0), u, lz(c1))]
    else:
        x = x0 if face == 3 else x1
        pts = [(x, lu(a0), lz(c0)), (x, lu(a1), lz(c0)), (x, lu(a1), lz(c1)), (x, lu(a0), lz(c1))]
    return np.array(pts, dtype=np.float64)


class _Builder:
    def __init__(self, direction: int, light: np.ndarray, ambient: float, night: bool, albedo: float):
        self.dir, self.light, self.ambient, self.night, self.albedo = direction, light, ambient, night, albedo
        self.quads, self.normals, self.values, self.face_of = [], [], [], []
        self.parts, self.lights, self.light_front = [], [], []
        self.part_of: list[int] = []
        self.is_decal: list[bool] = []
        self.lamp_value: list[float] = []
        self.exposure = 1.0
        self.face_index: dict = {}

    def _normal(self, face: int) -> np.ndarray:
        return [np.array([0, 0, 1.0]), np.array([0, self.dir, 0.0]), np.array([0, -self.dir, 0.0]),
                np.array([-1.0, 0, 0]), np.array([1.0, 0, 0])][face]

    def _shade(self, albedo: float, n: np.ndarray) -> float:
        lit = self.ambient + max(0.0, float(n @ self.light)) * (1.0 - self.ambient)
        return min(255.0, max(0.0, 255.0 * albedo * lit * self.exposure))

    def box(self, b: tuple, albedo: float | None = None, faces=(0, 1, 2, 3, 4)) -> int:
        albedo = self.albedo if albedo is None else albedo
        self.parts.append(_box(*b))
        first = len(self.quads)
        for f in faces:
            n = self._normal(f)
            self.quads.append(_face_quad(b, f))
            self.normals.append(n)
            self.values.append(self._shade(albedo, n))
            self.face_of.append(len(self.quads) - 1)
            self.part_of.append(len(self.parts) - 1)
            self.is_decal.append(False)
            self.lamp_value.append(0.0)
            self.face_index[(tuple(b), f)] = len(self.quads) - 1
        return first

    def decal(self, b: tuple, face: int, a0, a1, c0, c1, albedo: float, emissive: float | None = None) -> None:
        """A rectangle on face `face` of box b (must be drawn after that face)."""
        n = self._normal(face)
        idx = self.face_index[(tuple(b), face)]
        self.quads.append(_face_quad(b, face, a0, a1, c0, c1))
        self.normals.append(n)
        self.values.append(emissive if emissive is not None else self._shade(albedo, n))
        self.face_of.append(idx)
        self.part_of.append(self.part_of[idx])
        self.is_decal.append(True)
        self.lamp_value.append(0.0)

    def lamp(self, b: tuple, face: int, a0, a1, c0, c1, day_albedo: float, night_value: float, is_front: bool):
        self.decal(b, face, a0, a1, c0, c1, day_albedo, night_value if self.night else None)
        self.lamp_value[-1] = night_value
        self.lights.append(_face_quad(b, face, a0, a1, c0, c1).mean(axis=0))
        self.light_front.append(is_front)

    def shape(self, length: float, width: float, height: float, reverse_parts: bool = False) -> Shape:
        part_of = np.array(self.part_of)
        rank = -part_of if reverse_parts else part_of
        order = np.argsort(rank, kind="stable")
        self.quads = [self.quads[i] for i in order]
        self.normals = [self.normals[i] for i in order]
        self.values = [self.values[i] for i in order]
        self.face_of = list(part_of[order])
        decal = np.array(self.is_decal, dtype=bool)[order]
        lamp = np.array(self.lamp_value, dtype=np.float64)[order]
        q = np.array(self.quads)
        q[..., 1] *= self.dir  # local u (forward) -> signed road Y offset from the front point
        parts = np.array(self.parts)
        parts[..., 1] *= self.dir
        lights = np.array(self.lights).reshape(-1, 3)
        lights[:, 1] *= self.dir
        return Shape(q, np.array(self.normals), np.array(self.values), np.array(self.face_of), parts.reshape(-1, 3),
                     parts, lights, np.array(self.light_front, dtype=bool), length, width, height, decal, lamp)


def build_shape(cls: str, rng: np.random.Generator, direction: int, light: np.ndarray, ambient: float,
                night: bool, exposure: float = 1.0) -> Shape:
    """Random vehicle of class `cls` heading in `direction` (+1 receding, -1 approaching).

    `light` is the unit vector towards the sun (scaled by its strength), `ambient` the shadow-side level.
    Local coordinate u runs along the direction of travel with the front at u = 0 and the rear at -length.
    """
    (l0, l1), (w0, w1), (h0, h1) = CLASS_DIMS[cls]
    L, W, H = rng.uniform(l0, l1), rng.uniform(w0, w1), rng.uniform(h0, h1)
    albedo = float(rng.choice(ALBEDOS, p=ALBEDO_P) * rng.uniform(0.9, 1.1))
    b = _Builder(direction, light, ambient, night, albedo)
    b.exposure = exposure
    x0, x1 = -W / 2, W / 2
    glass, black, plate = 0.07, 0.05, 0.8
    head, tail = 250.0, 190.0
    if cls == "car":
        zb = H * rng.uniform(0.5, 0.58)
        body = (x0, x1, -L, 0.0, 0.0, zb)
        b.box(body)
        cf, cr = -L * rng.uniform(0.28, 0.36), -L * rng.uniform(0.78, 0.9)
        cab = (x0 + 0.12, x1 - 0.12, cr, cf, zb, H)
        b.box(cab)
        b.decal(body, 3, 0.12, 0.28, 0.0, 0.45, black)  # wheels, left side
        b.decal(body, 3, 0.74, 0.9, 0.0, 0.45, black)
        b.decal(body, 4, 0.12, 0.28, 0.0, 0.45, black)
        b.decal(body, 4, 0.74, 0.9, 0.0, 0.45, black)
        b.decal(cab, 1, 0.06, 0.94, 0.08, 0.92, glass)  # windscreen
        b.decal(cab, 2, 0.08, 0.92, 0.12, 0.9, glass)
        b.decal(cab, 3, 0.06, 0.94, 0.15, 0.88, glass)
        b.decal(cab, 4, 0.06, 0.94, 0.15, 0.88, glass)
        b.decal(body, 1, 0.1, 0.9, 0.05, 0.35, 0.12)  # grille/bumper
        b.decal(body, 1, 0.38, 0.62, 0.12, 0.3, plate)
        b.decal(body, 2, 0.38, 0.62, 0.2, 0.4, plate)
        b.lamp(body, 1, 0.04, 0.22, 0.55, 0.8, 0.75, head, True)
        b.lamp(body, 1, 0.78, 0.96, 0.55, 0.8, 0.75, head, True)
        b.lamp(body, 2, 0.03, 0.2, 0.55, 0.85, 0.3, tail, False)
        b.lamp(body, 2, 0.8, 0.97, 0.55, 0.85, 0.3, tail, False)
    elif cls == "motorcycle":
        bike = (-0.2, 0.2, -L, 0.0, 0.0, 0.9)
        b.box(bike, albedo=0.15)
        rider = (x0 + 0.05, x1 - 0.05, -L * 0.68, -L * 0.32, 0.9, H)
        b.box(rider)
        b.lamp(bike, 1, 0.1, 0.9, 0.6, 0.85, 0.8, head, True)
        b.lamp(bike, 2, 0.1, 0.9, 0.6, 0.8, 0.3, tail, False)
    elif cls == "van":
        body = (x0, x1, -L, 0.0, 0.0, H)
        b.box(body)
        b.decal(body, 1, 0.06, 0.94, 0.55, 0.92, glass)
        b.decal(body, 3, 0.0, 0.18, 0.55, 0.9, glass)
        b.decal(body, 4, 0.0, 0.18, 0.55, 0.9, glass)
        b.decal(body, 2, 0.1, 0.9, 0.55, 0.88, glass if rng.random() < 0.5 else albedo * 0.8)
        for side in (3, 4):
            b.decal(body, side, 0.1, 0.24, 0.0, 0.22, black)
            b.decal(body, side, 0.78, 0.92, 0.0, 0.22, black)
        b.decal(body, 1, 0.36, 0.64, 0.08, 0.16, plate)
        b.decal(body, 2, 0.36, 0.64, 0.1, 0.18, plate)
        b.lamp(body, 1, 0.03, 0.2, 0.3, 0.42, 0.75, head, True)
        b.lamp(body, 1, 0.8, 0.97, 0.3, 0.42, 0.75, head, True)
        b.lamp(body, 2, 0.02, 0.12, 0.25, 0.5, 0.3, tail, False)
        b.lamp(body, 2, 0.88, 0.98, 0.25, 0.5, 0.3, tail, False)
    else:  # truck, artic, bus
        if cls == "bus":
            body = (x0, x1, -L, 0.0, 0.0, H)
            b.box(body)
            b.decal(body, 1, 0.04, 0.96, 0.42, 0.92, glass)
            b.decal(body, 3, 0.02, 0.98, 0.5, 0.88, glass)
            b.decal(body, 4, 0.02, 0.98, 0.5, 0.88, glass)
            b.decal(body, 2, 0.1, 0.9, 0.6, 0.88, glass)
            b.decal(body, 0, 0.2, 0.8, 0.3, 0.45, albedo * 0.7)  # roof unit
            for side in (3, 4):
                b.decal(body, side, 0.1, 0.18, 0.0, 0.17, black)
                b.decal(body, side, 0.72, 0.8, 0.0, 0.17, black)
            front_box = body
        else:
            cab_len = 2.3 if cls == "truck" else 2.6
            cab_h = H * (0.8 if cls == "truck" else 0.95) if cls == "truck" else min(H, 3.6)
            cab_alb = albedo if rng.random() < 0.5 else float(rng.choice(ALBEDOS, p=ALBEDO_P))
            cab = (x0, x1, -cab_len, 0.0, 0.0, cab_h)
            gap = 0.3 if cls == "truck" else -0.8  # a trailer overhangs the tractor
            cargo_alb = float(rng.choice([0.88, 0.7, 0.5, 0.3]))
            cargo = (x0 + 0.02, x1 - 0.02, -L, -cab_len - gap, 0.5 if cls == "truck" else 1.1, H)
            b.box(cargo, albedo=cargo_alb)
            if cls == "artic":
                b.box((x0 + 0.25, x1 - 0.25, -cab_len - 1.2, -cab_len, 0.0, 1.1), albedo=0.12)  # fifth wheel
            b.box(cab, albedo=cab_alb)
            b.decal(cab, 1, 0.05, 0.95, 0.5, 0.9, glass)
            b.decal(cab, 3, 0.05, 0.6, 0.5, 0.88, glass)
            b.decal(cab, 4, 0.05, 0.6, 0.5, 0.88, glass)
            b.decal(cargo, 2, 0.03, 0.97, 0.03, 0.97, cargo_alb * 0.75)  # doors
            b.decal(cargo, 2, 0.49, 0.51, 0.03, 0.97, 0.1)
            if rng.random() < 0.6:  # livery stripe
                for side in (3, 4):
                    b.decal(cargo, side, 0.05, 0.95, 0.35, 0.6, float(rng.choice([0.1, 0.3, 0.9])))
            for side in (3, 4):
                b.decal(cab, side, 0.2, 0.45, 0.0, 0.22, black)
            front_box = cab
        b.decal(front_box, 1, 0.1, 0.9, 0.04, 0.18, 0.1)
        b.decal(front_box, 1, 0.4, 0.6, 0.06, 0.12, plate)
        b.lamp(front_box, 1, 0.03, 0.18, 0.12, 0.22, 0.75, head, True)
        b.lamp(front_box, 1, 0.82, 0.97, 0.12, 0.22, 0.75, head, True)
        rear_box = body if cls == "bus" else cargo
        b.lamp(rear_box, 2, 0.03, 0.12, 0.05, 0.15, 0.3, tail, False)
        b.lamp(rear_box, 2, 0.88, 0.97, 0.05, 0.15, 0.3, tail, False)
    # painter's order inside a vehicle: the part farther from the camera first (the camera is behind receding traffic)
    return b.shape(L, W, H, reverse_parts=direction > 0 and cls in ("truck", "artic"))
