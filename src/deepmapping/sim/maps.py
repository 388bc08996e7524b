"""Binary environment maps: a procedural indoor generator and PNG load/save.

Maps are uint8 images, 0 (black) = obstacle, 255 (white) = free; pixel (r, c) covers
x in [c, c+1), y in [r, r+1) (docs/conventions.md).
"""

from __future__ import annotations

import io
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage

from deepmapping.errors import InputError
from deepmapping.io.atomic import atomic_write, read_user_file

__all__ = ["procedural_indoor_map", "load_map_png", "save_map_png"]

FREE = 255
OBSTACLE = 0


@dataclass(frozen=True)
class _Box:
    """Half-open pixel box: rows [r0, r1), cols [c0, c1)."""

    r0: int
    r1: int
    c0: int
    c1: int

    def grow(self, m: int) -> "_Box":
        return _Box(self.r0 - m, self.r1 + m, self.c0 - m, self.c1 + m)

    def overlaps(self, o: "_Box") -> bool:
        return self.r0 < o.r1 and o.r0 < self.r1 and self.c0 < o.c1 and o.c0 < self.c1


class _Builder:
    """Recursive-subdivision (BSP) floor plan with doors, corridors and clutter."""

    def __init__(self, rng: np.random.Generator, size: int) -> None:
        self.rng = rng
        self.size = size
        self.occ = np.full((size, size), FREE, dtype=np.uint8)
        self.doors: list[_Box] = []
        self.rooms: list[_Box] = []
        self.min_room = max(40, int(round(size * 0.14)))
        self.corridors_left = int(rng.integers(1, 4)) if size >= 512 else 1
        self.door_margin = 10

    # -- walls and doors -------------------------------------------------------------
    def _thickness(self) -> int:
        return int(self.rng.integers(3, 7))

    def _wall(self, box: _Box) -> None:
        self.occ[box.r0 : box.r1, box.c0 : box.c1] = OBSTACLE

    def _door(self, wall: _Box, vertical: bool, lo_pad: int = 4) -> None:
        """Carve one door (30–60 px gap, shorter on short walls) through a wall box."""
        length = (wall.r1 - wall.r0) if vertical else (wall.c1 - wall.c0)
        width = int(self.rng.integers(30, 61))
        width = max(1, min(width, length - 2 * lo_pad))
        start = int(self.rng.integers(lo_pad, max(lo_pad, length - lo_pad - width) + 1))
        if vertical:
            door = _Box(wall.r0 + start, wall.r0 + start + width, wall.c0, wall.c1)
        else:
            door = _Box(wall.r0, wall.r1, wall.c0 + start, wall.c0 + start + width)
        self.occ[door.r0 : door.r1, door.c0 : door.c1] = FREE
        self.doors.append(door)

    def _blocks_door(self, wall: _Box) -> bool:
        grown = wall.grow(1)
        return any(grown.overlaps(d.grow(self.door_margin)) for d in self.doors)

    @staticmethod
    def _wall_box(room: _Box, vertical: bool, pos: int, t: int) -> _Box:
        if vertical:  # wall at columns [pos, pos + t) spanning the room's rows
            return _Box(room.r0, room.r1, pos, pos + t)
        return _Box(pos, pos + t, room.c0, room.c1)

    def _pick_wall(self, room: _Box, vertical: bool, t: int, lo: int, hi: int) -> int | None:
        """A wall position in [lo, hi] whose wall does not touch an existing door."""
        if hi < lo:
            return None
        for _ in range(24):
            pos = int(self.rng.integers(lo, hi + 1))
            if not self._blocks_door(self._wall_box(room, vertical, pos, t)):
                return pos
        return None

    # -- recursive subdivision --------------------------------------------------------
    def split(self, room: _Box, depth: int) -> None:
        h, w = room.r1 - room.r0, room.c1 - room.c0
        m = self.min_room
        can_v = w >= 2 * m + 6
        can_h = h >= 2 * m + 6
        if not (can_v or can_h):
            self.rooms.append(room)
            return
        if depth >= 2 and max(h, w) < 3 * m and self.rng.random() < 0.35:
            self.rooms.append(room)
            return
        if can_v and can_h:
            vertical = bool(self.rng.random() < w / (w + h))
        else:
            vertical = can_v
        extent = w if vertical else h
        base = room.c0 if vertical else room.r0

        # A corridor: two parallel walls around a 36–63 px strip, doors on both walls.
        if self.corridors_left > 0 and depth <= 2 and self.rng.random() < 0.5:
            cw = int(self.rng.integers(36, 64))
            t1, t2 = self._thickness(), self._thickness()
            span = t1 + cw + t2
            if extent >= 2 * m + span:
                pos = self._pick_wall(room, vertical, t1, base + m, base + extent - m - span)
                if pos is not None:
                    w1 = self._wall_box(room, vertical, pos, t1)
                    w2 = self._wall_box(room, vertical, pos + t1 + cw, t2)
                    if not self._blocks_door(w2):
                        self.corridors_left -= 1
                        self._wall(w1)
                        self._wall(w2)
                        for wall in (w1, w2):
                            for _ in range(int(self.rng.integers(1, 3))):
                                self._door(wall, vertical)
                        if vertical:
                            a = _Box(room.r0, room.r1, room.c0, pos)
                            b = _Box(room.r0, room.r1, pos + span, room.c1)
                        else:
                            a = _Box(room.r0, pos, room.c0, room.c1)
                            b = _Box(pos + span, room.r1, room.c0, room.c1)
                        self.split(a, depth + 1)
                        self.split(b, depth + 1)
                        return

        t = self._thickness()
        pos = self._pick_wall(room, vertical, t, base + m, base + extent - m - t)
        if pos is None:
            self.rooms.append(room)
            return
        wall = self._wall_box(room, vertical, pos, t)
        self._wall(wall)
        self._door(wall, vertical)
        if self.rng.random() < 0.25 and (wall.r1 - wall.r0 if vertical else wall.c1 - wall.c0) > 200:
            self._door(wall, vertical)
        if vertical:
            a = _Box(room.r0, room.r1, room.c0, pos)
            b = _Box(room.r0, room.r1, pos + t, room.c1)
        else:
            a = _Box(room.r0, pos, room.c0, room.c1)
            b = _Box(pos + t, room.r1, room.c0, room.c1)
        self.split(a, depth + 1)
        self.split(b, depth + 1)

    # -- clutter ----------------------------------------------------------------------
    def clutter(self) -> None:
        """Random boxes and discs inside leaf rooms, kept away from doors."""
        keep_out = [d.grow(28) for d in self.doors]
        for room in self.rooms:
            h, w = room.r1 - room.r0, room.c1 - room.c0
            small = min(h, w)
            if small < 48:
                continue
            n_items = int(self.rng.integers(0, 2 + (h * w) // 25000 + 1))
            for _ in range(n_items):
                for _attempt in range(10):
                    if self.rng.random() < 0.6:  # box
                        bh = int(self.rng.integers(6, max(7, small // 4)))
                        bw = int(self.rng.integers(6, max(7, small // 4)))
                        r0 = int(self.rng.integers(room.r0, room.r1 - bh + 1))
                        c0 = int(self.rng.integers(room.c0, room.c1 - bw + 1))
                        box = _Box(r0, r0 + bh, c0, c0 + bw)
                        if any(box.overlaps(k) for k in keep_out):
                            continue
                        self.occ[box.r0 : box.r1, box.c0 : box.c1] = OBSTACLE
                    else:  # disc
                        rad = float(self.rng.uniform(3.0, max(4.0, small / 9)))
                        cy = float(self.rng.uniform(room.r0 + rad, room.r1 - rad))
                        cx = float(self.rng.uniform(room.c0 + rad, room.c1 - rad))
                        r = int(np.ceil(rad))
                        box = _Box(int(cy) - r, int(cy) + r + 2, int(cx) - r, int(cx) + r + 2)
                        if any(box.overlaps(k) for k in keep_out):
                            continue
                        sl = (
                            slice(max(box.r0, 0), min(box.r1, self.size)),
                            slice(max(box.c0, 0), min(box.c1, self.size)),
                        )
                        rr, cc = np.ogrid[sl[0], sl[1]]
                        disc = (rr + 0.5 - cy) ** 2 + (cc + 0.5 - cx) ** 2 <= rad**2
                        self.occ[sl][disc] = OBSTACLE
                    break

    def keep_connected(self) -> None:
        """Fill every free component except the largest (4-connectivity) with obstacle."""
        labels, n = ndimage.label(self.occ == FREE)
        if n > 1:
            counts = np.bincount(labels.ravel())
            counts[0] = 0
            self.occ[(labels != int(np.argmax(counts))) & (labels > 0)] = OBSTACLE


def procedural_indoor_map(seed: int, size: int = 1024) -> np.ndarray:
    """An indoor-looking binary map (size x size uint8, 0 = obstacle, 255 = free).

    Outer wall around the border, rooms from recursive subdivision with 3–6 px walls,
    doors of 30–60 px so every room is reachable, 1–3 corridors, and clutter (boxes and
    discs) inside rooms away from the doors. The free space is one 4-connected component.
    Deterministic from ``seed``.
    """
    if size < 64:
        raise ValueError(f"map size must be >= 64 px, got {size}")
    rng = np.random.default_rng(seed)
    b = _Builder(rng, size)
    t = int(rng.integers(3, 7))
    b.occ[:t, :] = OBSTACLE
    b.occ[-t:, :] = OBSTACLE
    b.occ[:, :t] = OBSTACLE
    b.occ[:, -t:] = OBSTACLE
    b.split(_Box(t, size - t, t, size - t), depth=0)
    b.clutter()
    b.keep_connected()
    return b.occ


def load_map_png(path: str | os.PathLike) -> np.ndarray:
    """Load any image as a binary map: grayscale, then >= 128 -> 255 (free), else 0 (obstacle).

    Raises InputError ``"<path>: <problem>"`` for a missing or unreadable file.
    """
    from PIL import Image, UnidentifiedImageError

    raw = read_user_file(path)
    try:
        with Image.open(io.BytesIO(raw)) as im:
            im.load()
            if im.mode in ("RGBA", "LA", "P"):
                im = im.convert("RGBA")
                bg = Image.new("RGBA", im.size, (255, 255, 255, 255))  # transparent = free
                im = Image.alpha_composite(bg, im)
            gray = np.asarray(im.convert("L"))
    except (UnidentifiedImageError, OSError, ValueError) as e:
        raise InputError(f"{path}: cannot read image ({e})") from None
    if gray.ndim != 2 or gray.size == 0:
        raise InputError(f"{path}: image is empty")
    return np.where(gray >= 128, FREE, OBSTACLE).astype(np.uint8)


def save_map_png(path: str | os.PathLike, occ: np.ndarray) -> None:
    """Save a binary map as an 8-bit grayscale PNG (atomically: temp file + os.replace)."""
    from PIL import Image

    occ = np.asarray(occ)
    if occ.ndim != 2:
        raise ValueError(f"map must be a 2D array, got shape {occ.shape}")
    img = np.where(occ >= 128, FREE, OBSTACLE).astype(np.uint8) if occ.dtype != bool else (
        np.where(occ, FREE, OBSTACLE).astype(np.uint8)
    )
    atomic_write(Path(path), lambda f: Image.fromarray(img).save(f, format="PNG"))
