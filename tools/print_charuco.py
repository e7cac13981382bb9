"""Write a ChArUco board as a PNG to print at exact scale, from the same numbers the `hand-eye` routine reads.

    .venv/bin/python tools/print_charuco.py --out board.png [--squares 12 9] [--square-mm 20] [--marker-mm 15]
                                            [--dictionary DICT_5X5_250] [--first-marker 0] [--dpi 508]
                                            [--margin-mm 10]

The PNG carries its resolution (pixels per inch), so printed at 100 % ("actual size", no fit to page) each square
is --square-mm wide. Check one with a caliper after printing; the calibration fits the print's scale anyway (its
report says it as "board printed at ... of its drawing"). Glue the print flat on something rigid and matte: a
board that bends or shines is the error no fit removes. The image is checked by detecting every corner in it
before it is written.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
from PIL import Image

from geometry.charuco import DICTIONARIES, BoardDrawing

from calibration.errors import VisionError
from calibration.vision.charuco import find_corners


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, type=Path)
    parser.add_argument("--squares", type=int, nargs=2, default=(12, 9), metavar=("X", "Y"))
    parser.add_argument("--square-mm", type=float, default=20.0)
    parser.add_argument("--marker-mm", type=float, default=15.0)
    parser.add_argument("--dictionary", choices=DICTIONARIES, default="DICT_5X5_250")
    parser.add_argument("--first-marker", type=int, default=0)
    parser.add_argument("--dpi", type=int, default=508)
    parser.add_argument("--margin-mm", type=float, default=10.0, help="white border (the detector needs one)")
    args = parser.parse_args()
    if not 0 < args.marker_mm < args.square_mm:
        parser.error(f"--marker-mm {args.marker_mm} must be positive and smaller than --square-mm {args.square_mm}")
    drawing = BoardDrawing(tuple(args.squares), args.square_mm * 1e-3, args.marker_mm * 1e-3, args.dictionary,
                           args.first_marker)
    px_per_mm = args.dpi / 25.4
    square_px = args.square_mm * px_per_mm
    if abs(square_px - round(square_px)) > 1e-6:
        # generateImage draws whole pixels per square: keep the scale exact by choosing the dpi
        parser.error(f"--square-mm {args.square_mm} at {args.dpi} dpi is {square_px:.3f} px, not a whole number: "
                     "choose a dpi that makes it whole (254, 508 or 1016 dpi, 10, 20 or 40 px per mm, do for any "
                     "whole-mm square)")
    margin = round(args.margin_mm * px_per_mm)
    size = (round(args.squares[0] * square_px) + 2 * margin, round(args.squares[1] * square_px) + 2 * margin)
    image = drawing.board().generateImage(size, marginSize=margin, borderBits=1)
    try:
        corners = find_corners(cv2.GaussianBlur(image, (0, 0), 1.0), drawing)
    except VisionError as exc:
        print(f"print_charuco: the drawn board does not detect: {exc}", file=sys.stderr)
        return 1
    expected = (args.squares[0] - 1) * (args.squares[1] - 1)
    Image.fromarray(image).save(args.out, dpi=(args.dpi, args.dpi))
    print(f"wrote {args.out}: {size[0]} x {size[1]} px at {args.dpi} dpi = {size[0] / px_per_mm:.1f} x "
          f"{size[1] / px_per_mm:.1f} mm; {len(corners.ids)} of {expected} corners detect. Print at 100 %.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
