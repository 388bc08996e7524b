"""What every depth-image layout shares: which frames and pixels to keep, the camera, back-projection.

Layouts (``rgbd`` AVD-like, ``7scenes`` 7-Scenes/3DMatch, ``tum-rgbd`` TUM RGB-D) differ only in
where the depth images, the camera and the poses are; the same ``DepthOptions`` pick frames and
pixels in all of them (CLI: ``--every``, ``--frames``, ``--pixel-stride``, ``--image-size``,
``--max-depth``, ``--intrinsics``).

A depth pixel (u, v) with depth z becomes the camera-frame point
((u - cx) z / fx, (v - cy) z / fy, z) (OpenCV axes: x right, y down, z forward), always from the
pixel's coordinates in the full image: keeping fewer pixels never changes the camera.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
from pathlib import Path

import numpy as np

from deepmapping.data import ScanSet
from deepmapping.errors import ConfigError, InputError
from deepmapping.io.atomic import read_user_text
from deepmapping.io.loaders import natural_key

__all__ = ["DepthOptions", "Camera", "INTRINSICS_PRESETS", "DEFAULT_WIDTH", "parse_frames", "parse_image_size",
           "select_frames", "pixel_grid", "read_k_matrix", "read_json", "read_intrinsics_json", "read_depth_png",
           "camera_from", "backproject", "depth_scanset"]

DEFAULT_WIDTH = 80  # layouts without a size of their own keep about this many pixels across (640 -> 80x60)
INVALID_CODE = 65535  # "no measurement" in 7-Scenes (and saturated in uint16 images generally)


@dataclasses.dataclass(frozen=True)
class DepthOptions:
    """Which frames and pixels of a depth-image folder to read (None = the layout's default).

    every: keep every k-th frame (of the ``frames`` range). frames: (start, stop) positions in the
    layout's frame list, 0-based, stop excluded, either None (Python slice). pixel_stride: keep
    every s-th row and column from the top-left pixel; image_size: (width, height), the pixel
    nearest each cell centre of a width x height grid (one of the two). max_depth_m: deeper
    pixels are invalid. intrinsics: a preset name (``INTRINSICS_PRESETS``) or a file (3x3 K
    text or intrinsics.json) replacing the layout's camera.
    """

    every: int = 1
    frames: tuple[int | None, int | None] | None = None
    pixel_stride: int | None = None
    image_size: tuple[int, int] | None = None
    max_depth_m: float | None = None
    intrinsics: str | None = None

    def __post_init__(self):
        if not (isinstance(self.every, int) and self.every >= 1):
            raise ConfigError(f"every must be an integer >= 1, got {self.every!r}")
        if self.pixel_stride is not None and not (isinstance(self.pixel_stride, int) and self.pixel_stride >= 1):
            raise ConfigError(f"pixel stride must be an integer >= 1, got {self.pixel_stride!r}")
        if self.pixel_stride is not None and self.image_size is not None:
            raise ConfigError("give a pixel stride or an image size, not both")
        if self.image_size is not None and not all(isinstance(n, int) and n >= 1 for n in self.image_size):
            raise ConfigError(f"image size must be two integers >= 1, got {self.image_size!r}")
        if self.max_depth_m is not None and not (np.isfinite(self.max_depth_m) and self.max_depth_m > 0):
            raise ConfigError(f"max depth must be a positive number of metres, got {self.max_depth_m!r}")

    def is_default(self) -> bool:
        return self == DepthOptions()

    def to_dict(self) -> dict:
        """JSON-friendly (run.json keeps it so that ``deepmapping evaluate`` reads the same frames)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict | None) -> "DepthOptions":
        d = dict(d or {})
        for key in ("frames", "image_size"):
            if d.get(key) is not None:
                d[key] = tuple(d[key])
        return cls(**d)


def parse_frames(spec: str) -> tuple[int | None, int | None]:
    """``"START:STOP"`` (either part may be empty) -> (start, stop); ConfigError otherwise."""
    m = re.fullmatch(r"\s*(-?\d*)\s*:\s*(-?\d*)\s*", str(spec))
    if not m:
        raise ConfigError(f"--frames expects START:STOP (0-based, STOP excluded, e.g. 0:48), got {spec!r}")
    return tuple(int(g) if g not in ("", "-") else None for g in m.groups())


def parse_image_size(spec: str) -> tuple[int, int]:
    """``"80x60"`` -> (80, 60); ConfigError otherwise."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", str(spec))
    if not m or min(int(m[1]), int(m[2])) < 1:
        raise ConfigError(f"--image-size expects WIDTHxHEIGHT (e.g. 80x60), got {spec!r}")
    return int(m[1]), int(m[2])


def select_frames(source, total: int, opts: DepthOptions) -> np.ndarray:
    """Positions (0-based, increasing) of the frames ``opts`` keeps out of ``total``; at least two."""
    start, stop = opts.frames or (None, None)
    idx = np.arange(total)[slice(start, stop)][:: opts.every]
    if len(idx) < 2:
        raise InputError(f"{source}: {len(idx)} frame(s) of {total} selected (frames {start}:{stop}, every "
                         f"{opts.every}); need at least two")
    return idx


def pixel_grid(source, height: int, width: int, opts: DepthOptions, default_stride: int = 1):
    """(rows, cols): the pixel coordinates kept, from ``image_size``, ``pixel_stride`` or the default."""
    if opts.image_size is not None:
        w, h = opts.image_size
        if w > width or h > height:
            raise ConfigError(f"{source}: image size {w}x{h} is larger than the images ({width}x{height})")
        # the pixel nearest the centre of each of w x h equal cells: symmetric, no interpolation of depths
        return (np.floor((np.arange(h) + 0.5) * height / h).astype(int),
                np.floor((np.arange(w) + 0.5) * width / w).astype(int))
    s = opts.pixel_stride or default_stride
    return np.arange(0, height, s), np.arange(0, width, s)


@dataclasses.dataclass(frozen=True)
class Camera:
    """Pinhole depth camera: focal lengths and principal point in pixels, depth units per metre."""

    fx: float
    fy: float
    cx: float
    cy: float
    depth_scale: float  # a pixel value of depth_scale is 1 m
    width: int | None = None  # the image size the camera was given for (checked when known)
    height: int | None = None


# fr1/fr2/fr3: TUM's calibration of each Kinect's colour camera (distortion not applied here);
# "tum": the values TUM gives for turning its (OpenNI-registered) depth images into points,
# the same for all its sequences; "7scenes": Microsoft's 7-Scenes depth camera.
INTRINSICS_PRESETS = {
    "tum": Camera(525.0, 525.0, 319.5, 239.5, 5000.0, 640, 480),
    "fr1": Camera(517.306408, 516.469215, 318.643040, 255.313989, 5000.0, 640, 480),
    "fr2": Camera(520.908620, 521.007327, 325.141442, 249.701764, 5000.0, 640, 480),
    "fr3": Camera(535.4, 539.2, 320.1, 247.6, 5000.0, 640, 480),
    "7scenes": Camera(585.0, 585.0, 320.0, 240.0, 1000.0, 640, 480),
}


_INTR_KEYS = ("width", "height", "fx", "fy", "cx", "cy")


def read_json(path: Path, required: bool = True) -> dict:
    """A JSON object from ``path``; {} when absent and not ``required``; InputError otherwise."""
    if not path.is_file():
        if required:
            raise InputError(f"{path}: file not found")
        return {}
    try:
        obj = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as e:  # RecursionError: nested too deep
        raise InputError(f"{path}: invalid JSON ({type(e).__name__}: {e})".splitlines()[0]) from None
    if not isinstance(obj, dict):
        raise InputError(f"{path}: expected a JSON object")
    return obj


def read_intrinsics_json(path: Path, default_scale: float = 1000.0) -> dict:
    """``intrinsics.json`` as floats (width, height, fx, fy, cx, cy, depth_scale); InputError naming it."""
    intr = read_json(path)
    missing = [k for k in _INTR_KEYS if k not in intr]
    if missing:
        raise InputError(f"{path}: missing keys {', '.join(missing)}")
    try:
        out = {k: float(intr[k]) for k in _INTR_KEYS}
        out["depth_scale"] = float(intr.get("depth_scale", default_scale))
    except (TypeError, ValueError, OverflowError):  # OverflowError: an integer too large for a float
        raise InputError(f"{path}: intrinsics must be numbers") from None
    if not all(np.isfinite(v) for v in out.values()) or min(out["fx"], out["fy"], out["depth_scale"]) <= 0:
        raise InputError(f"{path}: fx, fy and depth_scale must be positive finite numbers")
    if not (1 <= out["width"] <= 2**20 and 1 <= out["height"] <= 2**20):
        raise InputError(f"{path}: width and height must be image sizes in pixels")
    return out


def read_depth_png(path: Path) -> np.ndarray:
    """(H, W) uint16 depth image; InputError naming the file if unreadable or not 16-bit grey."""
    from PIL import Image

    try:
        with Image.open(path) as img:
            img.load()
            mode = img.mode
            arr = np.array(img)
    except Exception as e:  # PIL raises OSError, SyntaxError, ValueError, ... on corrupt data
        raise InputError(f"{path}: cannot read PNG ({type(e).__name__}: {e})".splitlines()[0]) from None
    if not mode.startswith("I;16") or arr.ndim != 2:
        raise InputError(f"{path}: depth must be a 16-bit single-channel PNG (uint16 mm), got mode {mode}")
    return arr.astype(np.uint16)


def read_k_matrix(path: Path, depth_scale: float) -> Camera:
    """A 3x3 K text file (``camera-intrinsics.txt``: 9 numbers, rows fx 0 cx / 0 fy cy / 0 0 1)."""
    text = read_user_text(path)
    try:
        k = np.array([float(t) for t in text.replace(",", " ").split()], dtype=np.float64)
    except ValueError:
        raise InputError(f"{path}: expected a 3x3 camera matrix K (9 numbers)") from None
    if k.size != 9:
        raise InputError(f"{path}: expected a 3x3 camera matrix K (9 numbers), got {k.size}")
    k = k.reshape(3, 3)
    if not np.isfinite(k).all() or min(k[0, 0], k[1, 1]) <= 0 or np.abs(k[2] - [0, 0, 1]).max() > 1e-6:
        raise InputError(f"{path}: not a camera matrix (need fx, fy > 0 and a last row 0 0 1)")
    return Camera(float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]), depth_scale)


def _read_camera_file(path: Path, depth_scale: float) -> Camera:
    """An intrinsics.json (as the rgbd layout's) or a 3x3 K text file."""
    if path.suffix.lower() == ".json":
        intr = read_intrinsics_json(path, default_scale=depth_scale)
        return Camera(intr["fx"], intr["fy"], intr["cx"], intr["cy"], intr["depth_scale"],
                      int(intr["width"]), int(intr["height"]))
    return read_k_matrix(path, depth_scale)


def camera_from(option: str | None, found: list[Path], default: Camera | None, depth_scale: float,
                missing: Path) -> Camera:
    """The camera: ``option`` (a preset or a file) first, then the first existing file of ``found``,
    then ``default``; InputError naming ``missing`` when there is none."""
    if option is not None:
        if option.lower() in INTRINSICS_PRESETS:
            return INTRINSICS_PRESETS[option.lower()]
        path = Path(option)
        if not path.is_file():
            raise InputError(f"{path}: intrinsics file not found (or a preset: {', '.join(INTRINSICS_PRESETS)})")
        return _read_camera_file(path, depth_scale)
    for path in found:
        if path.is_file():
            return _read_camera_file(path, depth_scale)
    if default is None:
        raise InputError(f"{missing}: file not found (the depth camera's 3x3 K; or pass --intrinsics "
                         f"FILE or a preset: {', '.join(INTRINSICS_PRESETS)})")
    return default


def backproject(images: np.ndarray, rows, cols, cam: Camera, max_depth_m: float | None = None):
    """(K, h*w, 3) float32 camera-frame points and (K, h*w) valid mask of the kept pixels.

    Invalid: 0 (no return), 65535 (7-Scenes' "no measurement") and deeper than ``max_depth_m``.
    """
    raw = images[:, rows][:, :, cols]
    z = raw.astype(np.float64) / cam.depth_scale
    valid = (raw > 0) & (raw != INVALID_CODE)
    if max_depth_m is not None:
        valid &= z <= max_depth_m
    z = np.where(valid, z, 0.0)  # an invalid pixel is the all-zero point (ScanSet convention)
    v, u = np.meshgrid(np.asarray(rows, np.float64), np.asarray(cols, np.float64), indexing="ij")
    pts = np.stack([(u - cam.cx) * z / cam.fx, (v - cam.cy) * z / cam.fy, z], axis=-1)
    k = len(images)
    return pts.reshape(k, -1, 3).astype(np.float32), valid.reshape(k, -1)


def read_depth_images(files: list[Path]) -> np.ndarray:
    """(K, H, W) uint16 images of ``files``; InputError naming the first unreadable or odd-sized one."""
    images = []
    for f in files:
        img = read_depth_png(f)
        if images and img.shape != images[0].shape:
            raise InputError(f"{f}: image size {img.shape[1]}x{img.shape[0]} differs from "
                             f"{files[0].name} ({images[0].shape[1]}x{images[0].shape[0]})")
        images.append(img)
    return np.stack(images)


def depth_scanset(folder: Path, files: list[Path], cam: Camera, opts: DepthOptions, gt=None, init=None,
                  pose_dof: int = 6, default_stride: int | None = None) -> ScanSet:
    """The ScanSet of the depth images ``files`` (already selected): metres, reported in mm.

    ``default_stride`` None: about ``DEFAULT_WIDTH`` pixels across unless ``opts`` says otherwise.
    """
    images = read_depth_images(files)
    h, w = images.shape[1:]
    if cam.width is not None and (w, h) != (cam.width, cam.height):
        raise InputError(f"{files[0]}: image is {w}x{h} but the camera was given for {cam.width}x{cam.height}")
    stride = max(1, w // DEFAULT_WIDTH) if default_stride is None else default_stride
    rows, cols = pixel_grid(folder, h, w, opts, stride)
    points, valid = backproject(images, rows, cols, cam, opts.max_depth_m)
    return ScanSet(points=points, valid=valid, gt_poses=gt, init_poses=init, unit_scale=1000.0, unit="mm",
                   ordered=True, names=[f.name for f in files], source=str(folder),
                   grid_shape=(len(rows), len(cols)), pose_dof=pose_dof).validate()


def natural_sorted(paths) -> list[Path]:
    return sorted(paths, key=lambda p: natural_key(p.name))


def as_path(path: str | os.PathLike) -> Path:
    """``path`` as a Path; InputError when it is not a folder."""
    path = Path(path)
    if not path.is_dir():
        raise InputError(f"{path}: not a folder")
    return path
