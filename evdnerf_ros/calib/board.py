"""The ChArUco calibration board: its definition, its picture and its corner coordinates.

A ChArUco board is a chessboard whose white squares carry ArUco markers: the markers say which
chessboard corner is which, so a partly hidden or partly out-of-view board still gives
labelled corners. The board is drawn by OpenCV (``cv2.aruco.CharucoBoard.generateImage``)
and detected by OpenCV (``cv2.aruco.CharucoDetector``); opencv-contrib-python-headless
provides both.

Default board (:data:`DEFAULT_BOARD`): 7 x 5 squares of 30 mm, ArUco markers of 22 mm from
``DICT_5X5_100``: 210 x 150 mm, it fits on an A4 sheet or a laptop screen. Print it (or show
it full-screen) with ``evdnerf calibrate --board-image board.png`` and measure one printed
square: ``square_m`` must be the *printed* size.

Board frame (OpenCV's): origin at the board picture's top-left corner, x along its columns
(to the right), y along its rows (down), z into the board (x cross y), metres. Corner ``i``
(OpenCV's ChArUco id) lies at ``corners_3d()[i]``, on z = 0.

YAML (a calibration file's ``board`` section, or ``--board FILE``)::

    squares_x: 7          # squares along x (columns), >= 3
    squares_y: 5          # squares along y (rows), >= 3
    square_m: 0.03        # square side, metres (> 0)
    marker_m: 0.022       # marker side, metres (0 < marker_m < square_m)
    dictionary: DICT_5X5_100
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError

#: The ArUco dictionaries a board may use (OpenCV's predefined ones).
DICTIONARIES = tuple(f"DICT_{b}X{b}_{n}" for b in (4, 5, 6, 7) for n in (50, 100, 250, 1000))


def cv2_aruco():
    """``cv2`` with the aruco module, or an InputError saying what to install."""
    try:
        import cv2
    except ImportError:
        raise InputError("camera calibration needs OpenCV with its contrib modules: "
                         "pip install opencv-contrib-python-headless") from None
    if not hasattr(cv2, "aruco") or not hasattr(cv2.aruco, "CharucoDetector"):
        raise InputError(f"OpenCV {cv2.__version__} has no aruco.CharucoDetector; install "
                         "opencv-contrib-python-headless >= 4.8 (and uninstall a plain "
                         "opencv-python that hides it)")
    return cv2


@dataclass(frozen=True)
class BoardSpec:
    """A ChArUco board: squares, their size and the marker dictionary."""

    squares_x: int = 7
    squares_y: int = 5
    square_m: float = 0.03
    marker_m: float = 0.022
    dictionary: str = "DICT_5X5_100"

    def __post_init__(self):
        for name in ("squares_x", "squares_y"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 3 <= v <= 100:
                raise InputError(f"board {name} must be a whole number in [3, 100], got {v!r}")
        for name in ("square_m", "marker_m"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.floating)) \
                    or not np.isfinite(v) or not 0 < v <= 10:
                raise InputError(f"board {name} must be a length in metres in (0, 10], got {v!r}")
        if not self.marker_m < self.square_m:
            raise InputError(f"board marker_m {self.marker_m} must be smaller than square_m "
                             f"{self.square_m} (a marker sits inside a white square)")
        if self.dictionary not in DICTIONARIES:
            raise InputError(f"board dictionary {self.dictionary!r} is not one of "
                             f"{', '.join(DICTIONARIES)}")
        markers = (self.squares_x * self.squares_y) // 2
        if markers > int(self.dictionary.rsplit("_", 1)[1]):
            raise InputError(f"a {self.squares_x}x{self.squares_y} board needs {markers} markers, "
                             f"more than {self.dictionary} holds; use a larger dictionary")

    # ------------------------------------------------------------------ geometry
    @property
    def size_m(self) -> tuple[float, float]:
        """(width, height) of the board's squares area, metres."""
        return self.squares_x * self.square_m, self.squares_y * self.square_m

    @property
    def n_corners(self) -> int:
        return (self.squares_x - 1) * (self.squares_y - 1)

    def corners_3d(self) -> np.ndarray:
        """(n_corners, 3) float64: corner i's position in the board frame (module doc)."""
        i = np.arange(self.n_corners)
        cx, cy = i % (self.squares_x - 1), i // (self.squares_x - 1)
        return np.stack([(cx + 1) * self.square_m, (cy + 1) * self.square_m,
                         np.zeros(i.size)], axis=1)

    # ------------------------------------------------------------------ OpenCV
    def cv_board(self):
        cv2 = cv2_aruco()
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((int(self.squares_x), int(self.squares_y)),
                                      float(self.square_m), float(self.marker_m), d)

    def image(self, px_per_square: int = 100, margin_px: int = 0) -> np.ndarray:
        """The board's picture, (rows, cols) uint8 (0 black, 255 white), drawn by OpenCV:
        exactly ``px_per_square`` pixels a square, plus a white margin of ``margin_px``."""
        if not 10 <= int(px_per_square) <= 2000 or not 0 <= int(margin_px) <= 10000:
            raise InputError(f"board picture: px_per_square must be in [10, 2000] and margin_px "
                             f"in [0, 10000], got {px_per_square}, {margin_px}")
        s, m = int(px_per_square), int(margin_px)
        size = (self.squares_x * s + 2 * m, self.squares_y * s + 2 * m)
        return self.cv_board().generateImage(size, marginSize=m, borderBits=1)

    def record(self) -> dict:
        """The board as a YAML mapping (module doc)."""
        return {k: (float(v) if isinstance(v, float) else v) for k, v in asdict(self).items()}


DEFAULT_BOARD = BoardSpec()


def board_from_mapping(data, where: str = "board") -> BoardSpec:
    """A BoardSpec from a YAML mapping (module doc); unknown keys and bad values name `where`."""
    if not isinstance(data, dict):
        raise InputError(f"{where}: expected a mapping with squares_x, squares_y, square_m, "
                         f"marker_m, dictionary; got {type(data).__name__}")
    allowed = set(asdict(DEFAULT_BOARD))
    unknown = sorted(set(map(str, data)) - allowed)
    if unknown:
        raise InputError(f"{where}: unknown key(s) {', '.join(unknown)}; allowed: "
                         f"{', '.join(sorted(allowed))}")
    try:
        return BoardSpec(**{**asdict(DEFAULT_BOARD), **data})
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from None


def load_board(path) -> BoardSpec:
    """A board YAML file (module doc), or a calibration file's ``board`` section."""
    from ..yamlcheck import load_yaml

    path = Path(path)
    data = load_yaml(path, what="board file")
    if isinstance(data, dict) and "board" in data and isinstance(data["board"], dict):
        return board_from_mapping(data["board"], f"{path}: board")
    return board_from_mapping(data, str(path))
