#!/usr/bin/env python3
"""Printable calibration chessboard for Lamina, as an SVG sheet at exact millimetre scale.

The sheet's width and height are given in mm and its viewBox uses the same numbers, so
one SVG user unit is one millimetre on paper. Beside the board: a 50 mm check square
and a 100 mm ruler to confirm the printer did not scale the page, and the board's
specification as the device configuration expects it (``[board]`` in the TOML file).

Standard library only, so it runs anywhere Python 3.11 does:

    python3 hardware/calibration_board.py -o board.svg                 # 13x11 corners, 2 mm
    python3 hardware/calibration_board.py --preset limb -o limb.svg    # 13x9 corners, 12 mm
    python3 hardware/calibration_board.py --inner-corners 11x8 --square-mm 5 -o b.svg

Print at 100 % ("actual size", never "fit to page") on matte paper, check the 50 mm
square with calipers, and glue the sheet flat on a rigid plate.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import escape

PRESETS = {
    # The simulated rig and the thesis-scale scanner (19.05 mm calibration cylinder).
    "sim": ((13, 11), 2.0),
    # Limb-scale box (the simulator's Rig.limb()): a 168 x 120 mm board.
    "limb": ((13, 9), 12.0),
}
PAGES_MM = {"a4": (210.0, 297.0), "letter": (215.9, 279.4), "a3": (297.0, 420.0)}
CHECK_SQUARE_MM = 50.0
CHECK_FRAME_MM = 1.0
RULER_MM = 100
MARGIN_MM = 12.0  # inside most printers' unprintable border
GAP_MM = 10.0


@dataclass(frozen=True)
class BoardSheet:
    """One printable sheet: the chessboard, its check square, ruler and specification."""

    inner_corners: tuple[int, int] = (9, 7)
    square_mm: float = 3.0
    page: str = "a4"

    @property
    def squares(self) -> tuple[int, int]:
        """Return the number of squares across and down (inner corners + 1)."""
        return self.inner_corners[0] + 1, self.inner_corners[1] + 1

    @property
    def board_mm(self) -> tuple[float, float]:
        """Return the board's width and height in mm."""
        return self.squares[0] * self.square_mm, self.squares[1] * self.square_mm

    @property
    def page_mm(self) -> tuple[float, float]:
        """Return the page's width and height in mm."""
        return PAGES_MM[self.page]

    @property
    def board_origin_mm(self) -> tuple[float, float]:
        """Return the board's top-left corner on the page (centred across, under the title)."""
        return (self.page_mm[0] - self.board_mm[0]) / 2.0, MARGIN_MM + GAP_MM

    def problems(self) -> list[str]:
        """Return every reason this sheet cannot be printed (empty when it can)."""
        found = []
        nx, ny = self.inner_corners
        if nx < 2 or ny < 2:
            found.append(f"inner corners {nx}x{ny}: need at least 2x2")
        if nx == ny:
            found.append(f"inner corners {nx}x{ny}: use different counts so the board's "
                         "orientation is unambiguous (e.g. 9x7)")  # fmt: skip
        if not 0.5 <= self.square_mm <= 100.0:
            found.append(f"square {self.square_mm} mm: use 0.5 to 100 mm")
        if self.page not in PAGES_MM:
            found.append(f"page {self.page!r}: use one of {', '.join(PAGES_MM)}")
        elif not found:
            width, height = self.page_mm
            needed_w = max(self.board_mm[0], CHECK_SQUARE_MM + GAP_MM + RULER_MM)
            needed_h = self.board_mm[1] + 3 * GAP_MM + CHECK_SQUARE_MM + 30.0
            if needed_w > width - 2 * MARGIN_MM or needed_h > height - 2 * MARGIN_MM:
                found.append(
                    f"a {self.board_mm[0]:g} x {self.board_mm[1]:g} mm board does not fit "
                    f"on {self.page}: use smaller squares or a larger page (--page a3)"
                )
        return found

    def black_squares_mm(self) -> list[tuple[float, float, float, float]]:
        """Return (x, y, width, height) in mm of every black square; the top-left is black."""
        x0, y0 = self.board_origin_mm
        s = self.square_mm
        return [
            (x0 + i * s, y0 + j * s, s, s)
            for j in range(self.squares[1])
            for i in range(self.squares[0])
            if (i + j) % 2 == 0
        ]

    def check_square_mm(self) -> tuple[float, float]:
        """Return the top-left corner of the 50 mm check square."""
        return MARGIN_MM, self.board_origin_mm[1] + self.board_mm[1] + 2 * GAP_MM

    def spec_lines(self) -> list[str]:
        """Return the specification printed on the sheet."""
        nx, ny = self.inner_corners
        bw, bh = self.board_mm
        return [
            f"Lamina calibration chessboard: {nx} x {ny} inner corners, "
            f"{_num(self.square_mm)} mm squares, board {_num(bw)} x {_num(bh)} mm",
            f"Device config: [board] inner_corners = [{nx}, {ny}], "
            f"square_mm = {_num(self.square_mm)}",
            f"Print at 100 % (actual size). The check square must measure "
            f"{_num(CHECK_SQUARE_MM)} mm (+/- 0.25 mm) edge to edge.",
            "Matte paper, glued flat on a rigid plate; keep it clean and uncreased.",
        ]


def _num(value: float) -> str:
    """Return a length in mm with up to 9 decimals and no trailing zeros (exact to 1e-9)."""
    text = f"{value:.9f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def _rect(x: float, y: float, w: float, h: float, fill: str, extra: str = "") -> str:
    """Return one SVG rectangle in mm."""
    return (
        f'<rect x="{_num(x)}" y="{_num(y)}" width="{_num(w)}" height="{_num(h)}" '
        f'fill="{fill}"{extra}/>'
    )


def _ruler(x0: float, y0: float) -> list[str]:
    """Return a 100 mm ruler: ticks every mm, longer every 5 and 10 mm, numbered every 10."""
    parts = ['<g id="ruler">', _rect(x0, y0, RULER_MM, 0.3, "black")]
    for mm in range(RULER_MM + 1):
        length = 6.0 if mm % 10 == 0 else 4.0 if mm % 5 == 0 else 2.5
        # Each tick is centred on its millimetre mark.
        parts.append(_rect(x0 + mm - 0.1, y0, 0.2, length, "black"))
        if mm % 10 == 0:
            parts.append(
                f'<text x="{_num(x0 + mm)}" y="{_num(y0 + 10)}" font-size="3" '
                f'text-anchor="middle" font-family="sans-serif">{mm}</text>'
            )
    parts.append("</g>")
    return parts


def board_svg(sheet: BoardSheet) -> str:
    """Return the sheet as an SVG document (one user unit = 1 mm)."""
    problems = sheet.problems()
    if problems:
        raise ValueError("; ".join(problems))
    width, height = sheet.page_mm
    nx, ny = sheet.inner_corners
    x0, y0 = sheet.board_origin_mm
    bw, bh = sheet.board_mm
    parts = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        f'<svg xmlns="http://www.w3.org/2000/svg" version="1.1" width="{_num(width)}mm" '
        f'height="{_num(height)}mm" viewBox="0 0 {_num(width)} {_num(height)}">',
        f"<title>Lamina calibration chessboard {nx}x{ny}, {_num(sheet.square_mm)} mm</title>",
        _rect(0, 0, width, height, "white"),
        f'<g id="board" data-inner-corners="{nx} {ny}" data-square-mm="{_num(sheet.square_mm)}" '
        f'data-origin-mm="{_num(x0)} {_num(y0)}">',
        # The white field is drawn too, so the board edge is defined even on tinted paper.
        _rect(x0, y0, bw, bh, "white"),
        *(_rect(*square, "black") for square in sheet.black_squares_mm()),
        "</g>",
    ]
    cx, cy = sheet.check_square_mm()
    inner = CHECK_SQUARE_MM - 2 * CHECK_FRAME_MM
    parts += [
        f'<g id="check-square" data-size-mm="{_num(CHECK_SQUARE_MM)}">',
        _rect(cx, cy, CHECK_SQUARE_MM, CHECK_SQUARE_MM, "black"),
        _rect(cx + CHECK_FRAME_MM, cy + CHECK_FRAME_MM, inner, inner, "white"),
        f'<text x="{_num(cx + CHECK_SQUARE_MM / 2)}" y="{_num(cy + CHECK_SQUARE_MM / 2)}" '
        'font-size="4" text-anchor="middle" font-family="sans-serif">50 mm</text>',
        "</g>",
        *_ruler(cx + CHECK_SQUARE_MM + GAP_MM, cy + 5.0),
        '<g id="spec" font-family="sans-serif" font-size="3.5">',
    ]
    text_y = cy + CHECK_SQUARE_MM + GAP_MM
    for k, line in enumerate(sheet.spec_lines()):
        parts.append(
            f'<text x="{_num(MARGIN_MM)}" y="{_num(text_y + 5 * k)}">{escape(line)}</text>'
        )
    parts += ["</g>", "</svg>", ""]
    return "\n".join(parts)


def _corners(text: str) -> tuple[int, int]:
    """Parse ``NxM`` inner corners."""
    try:
        nx, ny = (int(part) for part in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not NxM, e.g. 9x7") from None
    return nx, ny


def main(argv: list[str] | None = None) -> int:
    """Write the sheet; a bad request ends in one line naming the problem, exit status 2."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", choices=sorted(PRESETS), default="sim")
    parser.add_argument("--inner-corners", type=_corners, help="NxM, overrides the preset")
    parser.add_argument("--square-mm", type=float, help="square size, overrides the preset")
    parser.add_argument("--page", default="a4", help=f"one of {', '.join(PAGES_MM)}")
    parser.add_argument("-o", "--out", type=Path, help="SVG file to write (default: stdout)")
    args = parser.parse_args(argv)
    corners, square_mm = PRESETS[args.preset]
    sheet = BoardSheet(
        args.inner_corners or corners,
        args.square_mm if args.square_mm is not None else square_mm,
        args.page.lower(),
    )
    problems = sheet.problems()
    if problems:
        print(f"calibration_board: {'; '.join(problems)}", file=sys.stderr)
        return 2
    svg = board_svg(sheet)
    if args.out is None:
        sys.stdout.write(svg)
        return 0
    try:
        args.out.write_text(svg, encoding="utf-8")
    except OSError as error:
        print(f"calibration_board: cannot write {args.out}: {error.strerror}", file=sys.stderr)
        return 2
    print(f"wrote {args.out}: {sheet.spec_lines()[0]}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
