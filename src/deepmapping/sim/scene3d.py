"""Synthetic indoor scenes (triangle meshes) standing in for the Active Vision Dataset (section 4.2).

World frame (metres): x right, y DOWN (gravity +y), z forward, the OpenCV camera convention.
Cameras sit at height y = 0; the floor is the plane y = +camera_height and the ceiling
y = -(room_height - camera_height). A scene is one room, or two rooms side by side along x
joined by a 1.2 m door opening in the dividing wall. Furniture is axis-aligned boxes: tables
(top + four legs), open shelves (back, sides, boards), cabinets (solid) and one staircase
(stacked boxes, 0.18 m rise, 0.28 m run). Room sizes are multiples of the 0.3 m AVD grid.

``free_positions`` lists the walkable grid points [x, z] (multiples of ``grid_m``) at least
``margin`` away from every wall and piece of furniture, restricted to the largest
4-connected component so every position can reach every other by grid moves.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Scene3D", "make_scene", "box_mesh"]

_BOX_TRIS = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                      [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]], dtype=np.int32)
WALL = 0.1  # wall thickness (m)
DOOR_W, DOOR_H = 1.2, 2.05


@dataclass
class Scene3D:
    """A triangle mesh (vertices (V, 3) float64, triangles (T, 3) int32) plus its walkable grid."""

    vertices: np.ndarray
    triangles: np.ndarray
    free_positions: np.ndarray  # (P, 2) [x, z] on the grid, metres
    grid_m: float = 0.3
    camera_height: float = 1.0
    room_height: float = 2.6
    bounds: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)  # interior xmin, xmax, zmin, zmax
    seed: int = 0
    boxes: list = field(default_factory=list, repr=False)  # (kind, lo (3,), hi (3,))
    cache: dict = field(default_factory=dict, repr=False, compare=False)  # ray caster, ...


def box_mesh(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """The 8 corners and 12 triangles of the axis-aligned box [lo, hi]."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    v = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y0, z1], [x0, y0, z1],
                  [x0, y1, z0], [x1, y1, z0], [x1, y1, z1], [x0, y1, z1]], dtype=np.float64)
    return v, _BOX_TRIS.copy()


class _Layout:
    """Collects boxes (with their floor footprints) while a scene is laid out."""

    def __init__(self, floor_y: float, ceil_y: float) -> None:
        self.floor_y, self.ceil_y = floor_y, ceil_y
        self.boxes: list[tuple[str, np.ndarray, np.ndarray]] = []
        self.footprints: list[tuple[float, float, float, float]] = []  # x0, x1, z0, z1
        self.keepout: list[tuple[float, float, float, float]] = []
        self.n_walls = 0  # footprints[:n_walls] are walls: furniture may touch them

    def add(self, kind: str, x0, x1, z0, z1, h0=0.0, h1=None, footprint=True) -> None:
        """Box over [x0,x1]x[z0,z1] from height h0 to h1 above the floor (default: to the ceiling)."""
        top = self.ceil_y if h1 is None else self.floor_y - h1
        self.boxes.append((kind, np.array([x0, top, z0]), np.array([x1, self.floor_y - h0, z1])))
        if footprint:
            self.footprints.append((x0, x1, z0, z1))

    def fits(self, rect, room) -> bool:
        x0, x1, z0, z1 = rect
        if x0 < room[0] or x1 > room[1] or z0 < room[2] or z1 > room[3]:
            return False
        for a0, a1, b0, b1 in self.footprints[self.n_walls:] + self.keepout:
            if x0 < a1 + 0.1 and a0 < x1 + 0.1 and z0 < b1 + 0.1 and b0 < z1 + 0.1:
                return False
        return True

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        parts = [box_mesh(lo, hi) for _, lo, hi in self.boxes]
        verts = np.concatenate([v for v, _ in parts])
        tris = np.concatenate([t + 8 * i for i, (_, t) in enumerate(parts)]).astype(np.int32)
        return verts, tris


def _walls(lay: _Layout, rng, width: float, depth: float, split: float | None) -> None:
    t = WALL
    lay.add("wall", -t, width + t, -t, 0.0)
    lay.add("wall", -t, width + t, depth, depth + t)
    lay.add("wall", -t, 0.0, 0.0, depth)
    lay.add("wall", width, width + t, 0.0, depth)
    lay.add("floor", -t, width + t, -t, depth + t, h0=-t, h1=0.0, footprint=False)
    room_h = lay.floor_y - lay.ceil_y
    lay.add("ceiling", -t, width + t, -t, depth + t, h0=room_h, h1=room_h + t, footprint=False)
    if split is not None:
        zc = 0.3 * rng.integers(int(np.ceil((DOOR_W / 2 + 0.3) / 0.3)), int((depth - DOOR_W / 2 - 0.3) / 0.3) + 1)
        x0, x1 = split - t / 2, split + t / 2
        lay.add("wall", x0, x1, 0.0, zc - DOOR_W / 2)
        lay.add("wall", x0, x1, zc + DOOR_W / 2, depth)
        lay.add("lintel", x0, x1, zc - DOOR_W / 2, zc + DOOR_W / 2, h0=DOOR_H, footprint=False)
        lay.keepout.append((split - 1.2, split + 1.2, zc - DOOR_W / 2, zc + DOOR_W / 2))
    lay.n_walls = len(lay.footprints)


def _against_wall(rng, room, w: float, d: float) -> tuple[float, float, float, float]:
    """A random w (along the wall) x d (out of the wall) rectangle touching one wall of ``room``."""
    x0, x1, z0, z1 = room
    side = rng.integers(4)
    if side < 2:  # walls z = z0 / z = z1
        a = rng.uniform(x0, max(x0, x1 - w))
        return (a, a + w, z0, z0 + d) if side == 0 else (a, a + w, z1 - d, z1)
    a = rng.uniform(z0, max(z0, z1 - w))
    return (x0, x0 + d, a, a + w) if side == 2 else (x1 - d, x1, a, a + w)


def _place(lay: _Layout, rng, room, kind: str, tries: int = 40) -> None:
    for _ in range(tries):
        if kind == "table":
            w, d = rng.uniform(0.8, 1.6), rng.uniform(0.6, 0.9)
            w, d = (w, d) if rng.random() < 0.5 else (d, w)
            x, z = rng.uniform(room[0], room[1] - w), rng.uniform(room[2], room[3] - d)
            rect = (x, x + w, z, z + d)
        else:
            w, d = {"shelf": (rng.uniform(0.8, 1.6), rng.uniform(0.3, 0.4)),
                    "cabinet": (rng.uniform(0.6, 1.2), rng.uniform(0.45, 0.6)),
                    "stairs": (0.9, 0.28 * rng.integers(6, 10))}[kind]
            rect = _against_wall(rng, room, w, d) if kind != "stairs" else _against_wall(rng, room, d, w)
        if lay.fits(rect, room):
            _FURNITURE[kind](lay, rng, *rect)
            return


def _table(lay, rng, x0, x1, z0, z1):
    h, leg = 0.75, 0.05
    lay.add("table", x0, x1, z0, z1, h0=h - 0.04, h1=h)
    for lx, lz in ((x0, z0), (x1 - leg, z0), (x0, z1 - leg), (x1 - leg, z1 - leg)):
        lay.add("table", lx, lx + leg, lz, lz + leg, h1=h - 0.04, footprint=False)


def _shelf(lay, rng, x0, x1, z0, z1):
    h, t = rng.uniform(1.6, 2.0), 0.02
    lay.add("shelf", x0, x1, z0, z1, h0=0.0, h1=0.1)
    for k in range(1, 5):
        hb = 0.1 + k * (h - 0.1) / 4
        lay.add("shelf", x0, x1, z0, z1, h0=hb - t, h1=hb, footprint=False)
    lay.add("shelf", x0, x0 + t, z0, z1, h1=h, footprint=False)
    lay.add("shelf", x1 - t, x1, z0, z1, h1=h, footprint=False)


def _cabinet(lay, rng, x0, x1, z0, z1):
    lay.add("cabinet", x0, x1, z0, z1, h1=rng.uniform(0.8, 1.1))


def _stairs(lay, rng, x0, x1, z0, z1):
    """Stacked boxes climbing along the longer side; step i covers the last n-i runs."""
    along_x = (x1 - x0) > (z1 - z0)
    n = int(round(max(x1 - x0, z1 - z0) / 0.28))
    up = rng.random() < 0.5
    for i in range(n):
        lo, hi = (i * 0.28, n * 0.28) if up else (0.0, (n - i) * 0.28)
        r = (x0 + lo, x0 + hi, z0, z1) if along_x else (x0, x1, z0 + lo, z0 + hi)
        lay.add("stairs", *r, h0=i * 0.18, h1=(i + 1) * 0.18, footprint=i == 0)


_FURNITURE = {"table": _table, "shelf": _shelf, "cabinet": _cabinet, "stairs": _stairs}


def _free_grid(footprints, bounds, grid_m: float, margin: float) -> np.ndarray:
    from scipy import ndimage

    xs = grid_m * np.arange(int(np.ceil(bounds[0] / grid_m)), int(bounds[1] / grid_m) + 1)
    zs = grid_m * np.arange(int(np.ceil(bounds[2] / grid_m)), int(bounds[3] / grid_m) + 1)
    gx, gz = np.meshgrid(xs, zs, indexing="ij")
    r = np.asarray(footprints, dtype=np.float64)  # (F, 4)
    dx = np.maximum(np.maximum(r[:, 0] - gx[..., None], gx[..., None] - r[:, 1]), 0.0)
    dz = np.maximum(np.maximum(r[:, 2] - gz[..., None], gz[..., None] - r[:, 3]), 0.0)
    free = (np.hypot(dx, dz).min(axis=-1) >= margin - 1e-9)
    lab, n = ndimage.label(free)
    if n == 0:
        return np.zeros((0, 2))
    keep = lab == 1 + np.argmax(np.bincount(lab.ravel())[1:])
    return np.stack([gx[keep], gz[keep]], axis=1)


def make_scene(seed: int, two_rooms: bool | None = None, furniture: bool = True,
               room_size: tuple[float, float] | None = None, camera_height: float = 1.0,
               room_height: float = 2.6, grid_m: float = 0.3, margin: float = 0.4) -> Scene3D:
    """A random (seeded) indoor scene; ``two_rooms=None`` draws it (p = 0.5).

    Room 1 is 3.9-6.0 m wide (x) and 4.2-6.9 m deep (z), room 2 3.6-5.1 m wide; ``room_size``
    (width, depth) fixes a single room. Furniture per room: a table, 1-2 shelves, 1-2
    cabinets; one staircase per scene.
    """
    rng = np.random.default_rng([seed, 30])
    two = bool(rng.random() < 0.5) if two_rooms is None else two_rooms
    w1, depth = (grid_m * rng.integers(13, 21), grid_m * rng.integers(14, 24)) if room_size is None else room_size
    w2 = grid_m * rng.integers(12, 18) if two and room_size is None else 0.0
    lay = _Layout(floor_y=camera_height, ceil_y=camera_height - room_height)
    width = w1 + w2
    _walls(lay, rng, width, depth, w1 if w2 else None)
    rooms = [(0.0, w1 - (WALL / 2 if w2 else 0.0), 0.0, depth)] + ([(w1 + WALL / 2, width, 0.0, depth)] if w2 else [])
    if furniture:
        _place(lay, rng, rooms[int(rng.integers(len(rooms)))], "stairs")
        for room in rooms:
            for kind in ["table"] + ["shelf"] * int(rng.integers(1, 3)) + ["cabinet"] * int(rng.integers(1, 3)):
                _place(lay, rng, room, kind)
    verts, tris = lay.mesh()
    bounds = (0.0, float(width), 0.0, float(depth))
    free = _free_grid(lay.footprints, bounds, grid_m, margin)
    return Scene3D(verts, tris, free, grid_m, camera_height, room_height, bounds, seed, lay.boxes)
