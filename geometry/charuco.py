"""A printed ChArUco board as its drawing states it (cv2.aruco): what the simulator prints and the calibration
detects, both from the same few numbers.

The board frame is OpenCV's: origin at the outer corner of the first square, x along the first row, y down the
columns, z into the print (a camera that sees the printed face looks along +z). Corner ids and their positions
are cv2.aruco's (`getChessboardCorners`, in metres).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

DICTIONARIES = ("DICT_4X4_250", "DICT_5X5_250", "DICT_6X6_250")


@dataclass(frozen=True)
class BoardDrawing:
    squares: tuple[int, int]  # (x, y)
    square_m: float
    marker_m: float
    dictionary: str = "DICT_5X5_250"
    first_marker: int = 0

    @property
    def n_markers(self) -> int:
        return self.squares[0] * self.squares[1] // 2

    @property
    def size_m(self) -> tuple[float, float]:
        return self.squares[0] * self.square_m, self.squares[1] * self.square_m

    def board(self) -> cv2.aruco.CharucoBoard:
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        ids = np.arange(self.first_marker, self.first_marker + self.n_markers, dtype=np.int32)
        return cv2.aruco.CharucoBoard(tuple(self.squares), self.square_m, self.marker_m, dictionary, ids)

    def corners(self) -> np.ndarray:
        """(n, 3) inner chessboard corners in the board frame (m), by id."""
        return self.board().getChessboardCorners().astype(float)
