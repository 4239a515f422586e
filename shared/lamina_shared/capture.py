"""Raw captures: read, validate and write the format of ``docs/capture-format.md``.

A reader validates the whole capture before any work starts and reports every
problem at once, each naming the offending key. Validation reads only each frame's
PNG header (size, bit depth, colour type) and its last chunk, never the pixels, so a
10,000-view capture is checked in seconds and a frame declaring 30000x30000 pixels is
refused without being decoded. Frames must lie inside the capture folder (symbolic
links are resolved first); counts, sections, heights and angles are checked against
:class:`~lamina_shared.limits.DeviceLimits`. Frame pixels are decoded with OpenCV,
which both the device and the host distributions install; the manifest checks need
only the standard library.
"""

from __future__ import annotations

import json
import math
import os
import struct
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path, PurePosixPath
from typing import Any, ClassVar

import numpy as np

from lamina_shared.errors import LaminaError
from lamina_shared.limits import DeviceLimits, plan_problems, show
from lamina_shared.types import BoardSpec, ScanPlan, ViewSpec

FORMAT_NAME = "lightsection-capture"
FORMAT_VERSION = 1
MANIFEST = "capture.json"
LASER_CHANNELS = {"red": 2, "green": 1, "blue": 0}  # index into OpenCV's BGR order
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"
_COLOUR_TYPES = {0: "grayscale", 2: "RGB"}
_OTHER_COLOUR_TYPES = {3: "palette", 4: "grayscale with alpha", 6: "RGB with alpha"}


class FrameError(LaminaError, ValueError):
    """A frame file that cannot be decoded as the capture format says."""


class CaptureError(LaminaError, ValueError):
    """A capture that cannot be used; ``problems`` lists every reason found."""

    SHOWN = 20
    """Problems the message names; ``problems`` holds all of them."""

    def __init__(self, root: Path, problems: list[str]) -> None:
        self.root = root
        self.problems = problems
        listing = "; ".join(problems[: self.SHOWN])
        if len(problems) > self.SHOWN:
            listing += f"; and {len(problems) - self.SHOWN} more"
        super().__init__(f"capture {root} is not usable ({len(problems)} problem(s)): {listing}")


@dataclass(frozen=True)
class CaptureView:
    """One view of a capture: its place in the scan and its two frame files."""

    spec: ViewSpec
    laser_on: Path
    laser_off: Path | None


@dataclass(frozen=True)
class Capture:
    """A validated capture folder."""

    root: Path
    image_size: tuple[int, int]
    laser_channel: str
    board: BoardSpec | None
    grid_image: Path | None
    cylinder_diameter_mm: float | None
    cylinder_views: tuple[CaptureView, ...]
    scan_views: tuple[CaptureView, ...]
    meta: dict[str, Any] = field(default_factory=dict)

    def views(self, target: str) -> tuple[CaptureView, ...]:
        """Return the views recorded for ``"cylinder"`` or ``"object"``."""
        return self.cylinder_views if target == "cylinder" else self.scan_views

    def plan(self, target: str) -> ScanPlan | None:
        """Return the scan plan the views of ``target`` follow, or None if there are none."""
        views = self.views(target)
        return ScanPlan(tuple(v.spec for v in views)) if views else None


# --- reading --------------------------------------------------------------------------


@dataclass(frozen=True)
class PngHeader:
    """What a PNG's IHDR chunk declares, read without decoding any pixel."""

    width: int
    height: int
    bit_depth: int
    colour_type: int


def read_png_header(path: Path) -> PngHeader:
    """Return the IHDR fields of a PNG; raise FrameError if it is not a whole PNG file.

    Only the first 33 bytes and the last 12 are read: a file that does not end with
    the IEND chunk was cut short.
    """
    with path.open("rb") as fh:
        head = fh.read(33)
        if len(head) < 33 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
            raise FrameError("not a PNG file")
        fh.seek(-len(_PNG_END), os.SEEK_END)
        if fh.read(len(_PNG_END)) != _PNG_END:
            raise FrameError("truncated PNG: it does not end with its IEND chunk")
    width, height, depth, colour = struct.unpack(">IIBB", head[16:26])
    return PngHeader(width, height, depth, colour)


def _imread(path: Path) -> np.ndarray:
    """Return an image file as OpenCV decodes it, unchanged; FrameError if it cannot."""
    import cv2  # the device and host distributions both install opencv

    # Read by Python, decoded in memory: OpenCV's own file API takes the path as text and
    # crashed on a name that is not UTF-8 (any bytes are a valid Linux file name).
    try:
        data = np.frombuffer(path.read_bytes(), np.uint8)
        image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    except OSError as exc:
        raise FrameError(f"{path} cannot be read ({exc.strerror or exc})") from None
    except cv2.error as exc:
        raise FrameError(f"{path} cannot be decoded as an image ({exc})") from None
    if image is None:
        raise FrameError(f"{path} cannot be decoded as an image")
    return np.asarray(image)


def read_frame(path: Path, laser_channel: str = "red") -> np.ndarray:
    """Return a frame as a 2-D uint8 or uint16 array, the laser's channel for colour PNGs.

    Raises:
        FrameError: the file is not a PNG OpenCV can decode (damaged, unsupported).
    """
    image = _imread(path)
    if image.ndim == 3:
        image = image[:, :, LASER_CHANNELS[laser_channel]]
    if image.dtype not in (np.uint8, np.uint16):
        raise FrameError(f"{path} has pixel type {image.dtype}; 8- or 16-bit expected")
    return np.ascontiguousarray(image)


def read_colour(path: Path) -> np.ndarray | None:
    """Return an 8-bit colour PNG as (H, W, 3) uint8 sRGB, or None for a grey or 16-bit one.

    Raises:
        FrameError: the file is not a PNG OpenCV can decode.
    """
    image = _imread(path)
    if image.ndim != 3 or image.dtype != np.uint8:
        return None
    return np.ascontiguousarray(image[:, :, 2::-1])  # OpenCV's BGR(A) to RGB


def _finite(value: float) -> bool:
    """Return True for a finite number that converts to a float (no 400-digit integer)."""
    if isinstance(value, int):
        return abs(value) <= 2**53
    return math.isfinite(value)


class _Checker:
    """Collects problems while walking a manifest, so all of them are reported at once."""

    def __init__(self, root: Path, decode: bool, limits: DeviceLimits) -> None:
        self.root = root
        self.real_root = os.path.realpath(root)
        self._folders: dict[str, str] = {}
        self.decode = decode
        self.limits = limits
        self.problems: list[str] = []
        self.image_size: tuple[int, int] | None = None
        self.laser_channel = "red"
        self.bit_depth: tuple[int, str] | None = None  # the first frame's, and its key

    def number(self, data: dict[str, Any], key: str, where: str, positive: bool = False) -> float:
        value = data.get(key)
        if isinstance(value, bool) or not isinstance(value, int | float):
            self.problems.append(f"{where}.{key}: a number is required, found {show(value)}")
            return math.nan
        if not _finite(value) or (positive and value <= 0):
            kind = "a positive finite" if positive else "a finite"
            self.problems.append(f"{where}.{key}: {kind} number is required, found {show(value)}")
            return math.nan
        return float(value)

    def frame(self, rel: Any, where: str) -> Path | None:
        if not isinstance(rel, str) or not rel:
            self.problems.append(f"{where}: a relative file path is required, found {rel!r}")
            return None
        if len(rel) > 4096 or "\0" in rel:
            self.problems.append(f"{where}: {rel[:40]!r}... is not a usable file path")
            return None
        pure = PurePosixPath(rel)
        if pure.is_absolute() or ".." in pure.parts:
            self.problems.append(f"{where}: {rel!r} must stay inside the capture folder")
            return None
        path = self.root / pure
        if not self.inside(path):
            self.problems.append(
                f"{where}: {rel!r} is a link to a file outside the capture folder; "
                "copy the file into the capture instead"
            )
            return None
        if not path.is_file():
            self.problems.append(f"{where}: file {rel} is missing")
            return None
        try:
            header = read_png_header(path)
        except (OSError, FrameError) as exc:
            self.problems.append(f"{where}: {rel} is unreadable ({exc})")
            return None
        before = len(self.problems)
        self.check_header(header, rel, where)
        if self.decode and len(self.problems) == before:
            try:
                read_frame(path, self.laser_channel)
            except FrameError:
                self.problems.append(f"{where}: {rel} is unreadable (damaged or truncated PNG)")
        return path

    def inside(self, path: Path) -> bool:
        """Return True if ``path``, links resolved, lies inside the capture folder."""
        folder = str(path.parent)
        real_folder = self._folders.get(folder)
        if real_folder is None:
            # Frames share a few folders: resolve each once, not once per frame.
            real_folder = self._folders[folder] = os.path.realpath(folder)
        if not self._contains(real_folder):
            return False
        return not path.is_symlink() or self._contains(os.path.realpath(path))

    def _contains(self, real: str) -> bool:
        return real == self.real_root or real.startswith(self.real_root.rstrip(os.sep) + os.sep)

    def check_header(self, header: PngHeader, rel: str, where: str) -> None:
        """Record what is wrong with a frame's declared size, bit depth and colour type."""
        side = self.limits.max_image_side_px
        if self.image_size and (header.width, header.height) != self.image_size:
            self.problems.append(
                f"{where}: {rel} is {header.width}x{header.height}, image_size says "
                f"{self.image_size[0]}x{self.image_size[1]}"
            )
        elif (
            max(header.width, header.height) > side
            or header.width * header.height > self.limits.max_image_pixels
        ):
            self.problems.append(
                f"{where}: {rel} declares {header.width}x{header.height} pixels, more than "
                f"{side} a side or {self.limits.max_image_pixels} in all"
            )
        if header.colour_type not in _COLOUR_TYPES:
            name = _OTHER_COLOUR_TYPES.get(header.colour_type, f"unknown ({header.colour_type})")
            self.problems.append(f"{where}: {rel} is a {name} PNG; grayscale or RGB is required")
        if header.bit_depth not in (8, 16):
            self.problems.append(
                f"{where}: {rel} has bit depth {header.bit_depth}; 8 or 16 is required"
            )
        elif self.bit_depth is None:
            self.bit_depth = (header.bit_depth, where)
        elif header.bit_depth != self.bit_depth[0]:
            self.problems.append(
                f"{where}: {rel} has bit depth {header.bit_depth}, {self.bit_depth[1]} has "
                f"{self.bit_depth[0]}: all frames of a capture share one bit depth"
            )

    def views(self, data: Any, where: str) -> list[CaptureView]:
        if not isinstance(data, list):
            self.problems.append(f"{where}: a list of views is required")
            return []
        if len(data) > self.limits.max_views:
            # Refused before any frame is looked at: the count alone rules it out.
            self.problems.append(
                f"{where}: {len(data)} views, at most {self.limits.max_views} allowed"
            )
            return []
        views: list[CaptureView] = []
        specs: list[tuple[str, ViewSpec]] = []
        for k, item in enumerate(data):
            at = f"{where}[{k}]"
            if not isinstance(item, dict):
                self.problems.append(f"{at}: a view object is required")
                continue
            section = item.get("section")
            if isinstance(section, bool) or not isinstance(section, int) or section < 0:
                self.problems.append(f"{at}.section: a whole number >= 0 is required")
                section = -1
            z_mm = self.number(item, "z_mm", at)
            angle = self.number(item, "angle_deg", at)
            if section >= 0 and math.isfinite(z_mm + angle):
                specs.append((at, ViewSpec(section, z_mm, angle)))
            on = self.frame(item.get("laser_on"), f"{at}.laser_on")
            off = None
            if item.get("laser_off") is not None:
                off = self.frame(item.get("laser_off"), f"{at}.laser_off")
            if on is not None and section >= 0 and math.isfinite(z_mm + angle):
                views.append(CaptureView(ViewSpec(section, z_mm, angle), on, off))
        self.problems.extend(plan_problems(specs, self.limits, min_z_mm=0.0))
        return views

    def board(self, data: dict[str, Any]) -> tuple[BoardSpec | None, Path | None]:
        where = "calibration_grid"
        if data.get("pattern", "chessboard") != "chessboard":
            self.problems.append(f"{where}.pattern: unknown pattern {data.get('pattern')!r}")
        corners = data.get("inner_corners")
        if not (
            isinstance(corners, list)
            and len(corners) == 2
            and all(
                isinstance(c, int) and not isinstance(c, bool) and 1 <= c <= 1000 for c in corners
            )
        ):
            self.problems.append(
                f"{where}.inner_corners: two whole numbers in 1..1000 are required"
            )
            corners = None
        square = self.number(data, "square_mm", where, positive=True)
        origin = data.get("origin_mm", [0.0, 0.0])
        if not (
            isinstance(origin, list)
            and len(origin) == 2
            and all(isinstance(o, int | float) and _finite(o) for o in origin)
        ):
            self.problems.append(f"{where}.origin_mm: two finite numbers are required")
            origin = None
        image = self.frame(data.get("image"), f"{where}.image")
        if corners is None or origin is None or math.isnan(square):
            return None, image
        return BoardSpec((corners[0], corners[1]), square, (origin[0], origin[1])), image


def _load_manifest(root: Path, limits: DeviceLimits) -> dict[str, Any]:
    path = root / MANIFEST
    if not root.is_dir():
        raise CaptureError(root, [f"folder {root} does not exist"])
    if not path.is_file():
        raise CaptureError(root, [f"{MANIFEST} is missing"])
    real_root = os.path.realpath(root)
    if os.path.dirname(os.path.realpath(path)) != real_root:
        raise CaptureError(root, [f"{MANIFEST} is a link to a file outside the capture folder"])
    size = path.stat().st_size
    if size > limits.max_manifest_bytes:
        raise CaptureError(
            root, [f"{path} is {size} bytes, more than {limits.max_manifest_bytes}: not a manifest"]
        )
    try:
        data = json.loads(path.read_bytes().decode("utf-8"))
    except (OSError, UnicodeError, ValueError, RecursionError) as exc:
        # ValueError covers malformed JSON and integers too long to convert;
        # RecursionError a file nested deeper than any manifest.
        reason = "nested too deeply" if isinstance(exc, RecursionError) else str(exc)[:200]
        raise CaptureError(root, [f"{path} is not valid JSON ({reason})"]) from None
    if not isinstance(data, dict):
        raise CaptureError(root, [f"{MANIFEST} must hold a JSON object"])
    if data.get("format") != FORMAT_NAME:
        raise CaptureError(root, [f"format: {data.get('format')!r} is not {FORMAT_NAME!r}"])
    if data.get("version") != FORMAT_VERSION:
        raise CaptureError(
            root,
            [
                f"version: capture version {data.get('version')!r} is not supported "
                f"(this reader knows version {FORMAT_VERSION})"
            ],
        )
    return data


def load_capture(
    root: Path | str, decode_frames: bool = False, limits: DeviceLimits | None = None
) -> Capture:
    """Read and validate a capture folder; raise :class:`CaptureError` listing every problem.

    Args:
        root: the capture folder (holding ``capture.json``).
        decode_frames: also decode every frame, catching damage inside a file (slow:
            the headers and the end of each file are always checked).
        limits: the sizes allowed (views, sections, heights, frame sides).

    Returns:
        The validated capture, with frame paths inside ``root``.
    """
    root = Path(root)
    limits = limits or DeviceLimits()
    data = _load_manifest(root, limits)
    check = _Checker(root, decode_frames, limits)
    size = data.get("image_size")
    side = limits.max_image_side_px
    if (
        isinstance(size, list)
        and len(size) == 2
        and all(isinstance(s, int) and not isinstance(s, bool) and 0 < s <= side for s in size)
        and size[0] * size[1] <= limits.max_image_pixels
    ):
        check.image_size = (size[0], size[1])
    else:
        check.problems.append(
            f"image_size: two whole numbers in 1..{side}, at most {limits.max_image_pixels} "
            f"pixels in all, are required, found {str(size)[:40]}"
        )
    channel = data.get("laser_channel", "red")
    if channel not in LASER_CHANNELS:
        check.problems.append(f"laser_channel: {channel!r} is not one of red, green, blue")
    else:
        check.laser_channel = channel
    board, grid_image = None, None
    if isinstance(data.get("calibration_grid"), dict):
        board, grid_image = check.board(data["calibration_grid"])
    elif "calibration_grid" in data:
        check.problems.append("calibration_grid: an object is required")
    diameter, cylinder_views = None, []
    cylinder = data.get("calibration_cylinder")
    if isinstance(cylinder, dict):
        diameter = check.number(cylinder, "diameter_mm", "calibration_cylinder", positive=True)
        cylinder_views = check.views(cylinder.get("views"), "calibration_cylinder.views")
    elif cylinder is not None:
        check.problems.append("calibration_cylinder: an object is required")
    scan = data.get("scan")
    scan_views = check.views(scan.get("views") if isinstance(scan, dict) else None, "scan.views")
    if check.problems:
        raise CaptureError(root, check.problems)
    assert check.image_size is not None
    meta = data["meta"] if isinstance(data.get("meta"), dict) else {}
    return Capture(
        root,
        check.image_size,
        check.laser_channel,
        board,
        grid_image,
        diameter,
        tuple(cylinder_views),
        tuple(scan_views),
        meta,
    )


# --- writing --------------------------------------------------------------------------


class CaptureWriter:
    """Write frames and, on :meth:`close`, the manifest of a new capture folder.

    The manifest is written last and atomically, so a folder without one is an
    interrupted recording, never a capture that silently lacks views.
    """

    _FOLDERS: ClassVar[dict[str, str]] = {"cylinder": "cyl", "object": "scan"}

    def __init__(
        self,
        root: Path | str,
        image_size: tuple[int, int],
        meta: dict[str, Any] | None = None,
    ) -> None:
        self.root = Path(root)
        if (self.root / MANIFEST).exists():
            raise FileExistsError(f"{self.root} already holds a capture; choose a new folder")
        self.root.mkdir(parents=True, exist_ok=True)
        self.image_size = image_size
        self.meta = dict(meta or {})
        self._grid: dict[str, Any] | None = None
        self._cylinder_mm: float | None = None
        self._views: dict[str, list[dict[str, Any]]] = {"cylinder": [], "object": []}

    def _write_png(self, rel: str, image: np.ndarray) -> str:
        import cv2

        if image.shape[::-1] != self.image_size:
            raise CaptureError(
                self.root, [f"frame {rel} is {image.shape[::-1]}, expected {self.image_size}"]
            )
        path = self.root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        ok, png = cv2.imencode(".png", image)  # see _imread: the path stays Python's
        if not ok:
            raise OSError(f"could not write {path}")
        path.write_bytes(png.tobytes())
        return rel

    def add_grid(self, image: np.ndarray, board: BoardSpec) -> None:
        """Store the calibration board image and the board's geometry."""
        self._grid = {"image": self._write_png("calib/grid.png", image), **board.to_dict()}

    def set_cylinder(self, diameter_mm: float) -> None:
        """Record the calibration cylinder's diameter."""
        self._cylinder_mm = diameter_mm

    def add_view(
        self, target: str, view: ViewSpec, index: int, on: np.ndarray, off: np.ndarray | None
    ) -> None:
        """Store one view's laser-on (and laser-off) frame for ``cylinder`` or ``object``."""
        stem = f"{self._FOLDERS[target]}/s{view.section:03d}_v{index:02d}"
        entry: dict[str, Any] = {
            **view.to_dict(),
            "laser_on": self._write_png(f"{stem}_on.png", on),
        }
        if off is not None:
            entry["laser_off"] = self._write_png(f"{stem}_off.png", off)
        self._views[target].append(entry)

    def manifest(self) -> dict[str, Any]:
        """Return the manifest as it stands."""
        data: dict[str, Any] = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "image_size": list(self.image_size),
            "laser_channel": "red",
        }
        if self._grid:
            data["calibration_grid"] = self._grid
        if self._cylinder_mm is not None:
            data["calibration_cylinder"] = {
                "diameter_mm": self._cylinder_mm,
                "views": self._views["cylinder"],
            }
        data["scan"] = {"views": self._views["object"]}
        created = datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
        data["meta"] = {"created": created, **self.meta}
        return data

    def close(self) -> Path:
        """Write ``capture.json`` atomically and return its path."""
        path = self.root / MANIFEST
        tmp = path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(self.manifest(), indent=2) + "\n", encoding="utf-8")
        tmp.replace(path)
        return path
