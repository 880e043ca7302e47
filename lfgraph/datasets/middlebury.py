"""The Middlebury multi-view stereo sets (templeSparseRing, dinoSparseRing): views with published K, R, t."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from lfgraph.core.calibration import FILE_ROTATION_TOLERANCE, Calibration, nearest_rotation
from lfgraph.core.camera import Intrinsics
from lfgraph.core.geometry import invert_T, is_rotation, make_T
from lfgraph.core.grid import ViewGrid
from lfgraph.io.capture import CaptureError


def load_mview(folder: str | os.PathLike) -> tuple[Calibration, list[np.ndarray]]:
    """The published cameras and the grayscale images of a ``*SparseRing`` folder.

    ``*_par.txt`` lines are ``name k11..k33 r11..r33 t1 t2 t3`` with ``P = K [R | t]`` (world to image). The views
    are not a grid: they come as one row of N views in file order, a free arrangement (neighbours from the poses,
    `lfgraph.core.grid.free_grid`), poses relative to the first view. Rotations are accepted orthonormal to their
    printed precision (dinoSparseRing's to 1.4e-6) and made exact (the nearest rotation).

    Raises:
        CaptureError: no ``*_par.txt``, a malformed line, a matrix that is no rotation, or an unreadable image (names
            the file).
    """
    root = Path(folder)
    pars = sorted(root.glob("*_par.txt"))
    if not pars:
        raise CaptureError(f"{root}: no *_par.txt camera file")
    names, intr, view_T_world = [], [], []  # noqa: N806
    for lineno, line in enumerate(pars[0].read_text().splitlines()[1:], start=2):
        p = line.split()
        if not p:
            continue
        if len(p) != 22:
            raise CaptureError(f"{pars[0]}:{lineno}: expected 22 fields (name, K, R, t), got {len(p)}")
        K = np.array(p[1:10], float).reshape(3, 3)  # noqa: N806
        names.append(p[0])
        intr.append(Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
        R = np.array(p[10:19], float).reshape(3, 3)  # noqa: N806
        if not is_rotation(R, FILE_ROTATION_TOLERANCE):
            raise CaptureError(f"{pars[0]}:{lineno}: r11..r33 is not a rotation (R^T R must be I to "
                               f"{FILE_ROTATION_TOLERANCE:g} and det R = +1)")
        view_T_world.append(make_T(nearest_rotation(R), np.array(p[19:22], float)))
    images = []
    for n in names:
        img = cv2.imread(str(root / n), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise CaptureError(f"{root / n}: cannot read this image")
        images.append(img)
    h, w = images[0].shape
    ref_T_view = np.stack([view_T_world[0] @ invert_T(T) for T in view_T_world])  # noqa: N806
    return Calibration(ViewGrid(1, len(names), 0, "free"), (w, h), tuple(intr), ref_T_view), images
