"""Pictures in a terminal: a camera frame in half-block characters with the stripe drawn over it.

Each character cell shows two pixels stacked: the upper half block ``▀`` takes the top
pixel as its foreground colour and the bottom pixel as its background, so a cell is
about square and a 640x480 frame fits a 80x24 terminal at a useful size.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from rich.color import Color
from rich.style import Style
from rich.text import Text

UPPER_HALF = "▀"
STRIPE_RGB = (255, 40, 40)
"""The overlay colour of detected stripe points: red, like the laser."""


@dataclass(frozen=True)
class CellGrid:
    """A frame fitted into ``cols`` x ``rows`` cells: (rows*2, cols, 3) RGB pixels."""

    pixels: np.ndarray

    @property
    def rows(self) -> int:
        """Return the number of text rows."""
        return self.pixels.shape[0] // 2

    @property
    def cols(self) -> int:
        """Return the number of text columns."""
        return self.pixels.shape[1]


def fit_size(image_wh: tuple[int, int], cols: int, rows: int) -> tuple[int, int]:
    """Return the (cols, pixel rows) an image of ``image_wh`` fills within the cells, aspect kept.

    A cell is two pixels tall, so the pixel grid is ``cols`` x ``2 * rows``.
    """
    width, height = image_wh
    scale = min(cols / width, 2 * rows / height)
    out_cols = max(1, int(width * scale))
    out_rows = max(2, int(height * scale) // 2 * 2)
    return out_cols, out_rows


def to_gray8(image: np.ndarray) -> np.ndarray:
    """Return an 8-bit grayscale copy of an 8- or 16-bit, gray or BGR image."""
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    return img.astype(np.uint8, copy=False)


def cell_grid(
    image: np.ndarray, cols: int, rows: int, stripe_uv: np.ndarray | None = None
) -> CellGrid:
    """Downsample ``image`` into at most ``cols`` x ``rows`` cells and mark the stripe.

    Args:
        image: (H, W) or (H, W, 3) camera frame, 8 or 16 bit.
        cols: text columns available.
        rows: text rows available.
        stripe_uv: optional (N, 2) image points ``(u, v)`` (pixel centres at integers).

    Returns:
        The cell grid; stripe points are painted :data:`STRIPE_RGB`.
    """
    gray = to_gray8(image)
    height, width = gray.shape
    out_cols, out_rows = fit_size((width, height), cols, rows)
    small = cv2.resize(gray, (out_cols, out_rows), interpolation=cv2.INTER_AREA)
    pixels = np.repeat(small[:, :, None], 3, axis=2)
    if stripe_uv is not None and len(stripe_uv):
        uv = np.asarray(stripe_uv, dtype=float)
        # Pixel (i, j) covers [i - 0.5, i + 0.5): shift to edges before scaling to cells.
        c = np.floor((uv[:, 0] + 0.5) * out_cols / width).astype(int)
        r = np.floor((uv[:, 1] + 0.5) * out_rows / height).astype(int)
        keep = (c >= 0) & (c < out_cols) & (r >= 0) & (r < out_rows)
        pixels[r[keep], c[keep]] = STRIPE_RGB
    return CellGrid(pixels)


def grid_text(grid: CellGrid) -> Text:
    """Return the cell grid as Rich text of upper-half blocks, one line per cell row."""
    text = Text(no_wrap=True, overflow="crop")
    styles: dict[tuple[int, ...], Style] = {}
    top, bottom = grid.pixels[0::2], grid.pixels[1::2]
    for r in range(grid.rows):
        for key in map(tuple, np.concatenate([top[r], bottom[r]], axis=1).tolist()):
            style = styles.get(key)
            if style is None:
                fg, bg = Color.from_rgb(*key[:3]), Color.from_rgb(*key[3:])
                style = Style(color=fg, bgcolor=bg)
                styles[key] = style
            text.append(UPPER_HALF, style)
        if r < grid.rows - 1:
            text.append("\n")
    return text
