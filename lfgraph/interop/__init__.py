"""Calibration import and export in other tools' formats ("interoperability").

Two entry points: `export_calibration(calib, fmt, path)` and `import_calibration(path, fmt, grid)`; `input_paths`
names what an import reads (so a caller can refuse to overwrite it). Every file is written atomically (a temporary
sibling renamed onto the final name), so a crash never leaves half a file.

One module per format, each documenting its layout: `opencv_yaml` (``opencv-yaml``, export and import), `kalibr`
(``kalibr``, export and import), `colmap` (``colmap``, export and import), `json_format` (``json``, export and
import), `ros` (``ros``: a folder of ROS camera_info YAML files, export), `mrcal` (``mrcal``: a folder of
mrcal ``.cameramodel`` files, export), `middlebury` (``middlebury``, import) and `hci` (``hci``, import);
`common` holds the shared validation and
the grid rules of imports. Common conventions: views are always row-major on the grid; poses are in metres; pixels
follow OpenCV's convention, the centre of the top-left pixel is ``(0, 0)``, except where a format says otherwise.

Grids on import: ``grid`` is a `ViewGrid`, a ``(rows, cols)`` pair or None. Its view count and shape must match
the file's (the error names the file and the key). A `ViewGrid` whose reference differs from the file's re-expresses
all poses relative to that view (refused when the file holds a rectification, which is tied to its reference);
a ``(rows, cols)`` pair keeps the file's reference. At most `MAX_IMPORT_VIEWS` views are imported.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.grid_design import grid_problems
from lfgraph.interop import colmap, hci, json_format, kalibr, middlebury, mrcal, opencv_yaml, ros
from lfgraph.interop.colmap import COLMAP_CAMERA_MODELS, COLMAP_MODEL_FILES, COLMAP_PIXEL_OFFSET_PX
from lfgraph.interop.common import MAX_IMPORT_VIEWS, MM_PER_M, GridLike, PathLike, fail, in_folder
from lfgraph.interop.kalibr import KALIBR_DISTORTION_MODELS

__all__ = [
    "COLMAP_CAMERA_MODELS",
    "COLMAP_MODEL_FILES",
    "COLMAP_PIXEL_OFFSET_PX",
    "EXPORT_FORMATS",
    "IMPORT_FORMATS",
    "KALIBR_DISTORTION_MODELS",
    "MAX_IMPORT_VIEWS",
    "MM_PER_M",
    "FILE_FORMATS",
    "RECTIFICATION_FORMATS",
    "export_calibration",
    "import_calibration",
    "input_paths",
]

_WRITERS: dict[str, Callable[[Calibration, Path], None]] = {
    "opencv-yaml": opencv_yaml.write,
    "kalibr": kalibr.write,
    "colmap": colmap.write,
    "json": json_format.write,
    "ros": ros.write,
    "mrcal": mrcal.write,
}
_READERS: dict[str, Callable[[Path, GridLike], Calibration]] = {
    "opencv-yaml": opencv_yaml.read,
    "kalibr": kalibr.read,
    "colmap": colmap.read,
    "json": json_format.read,
    "middlebury": middlebury.read,
    "hci": hci.read,
}
EXPORT_FORMATS: tuple[str, ...] = tuple(_WRITERS)
IMPORT_FORMATS: tuple[str, ...] = tuple(_READERS)
FILE_FORMATS: tuple[str, ...] = ("opencv-yaml", "kalibr", "json")  # exports that write one file (colmap: a folder)
# exports that write a stored rectification (ros: as each camera_info's R and P, not read back); the others have no
# place for one, and an export to them says so
RECTIFICATION_FORMATS: tuple[str, ...] = ("opencv-yaml", "json", "ros")


def export_calibration(calib: Calibration, fmt: str, path: PathLike) -> Path:
    """Write a calibration in another tool's format (see each format's module).

    Args:
        calib: the calibration to write.
        fmt: one of `EXPORT_FORMATS`: ``opencv-yaml``, ``kalibr``, ``colmap``, ``json``, ``ros``, ``mrcal``.
        path: the output file; for ``colmap``, ``ros`` and ``mrcal`` a folder (created, or replaced if it holds only
            files of that export).

    Returns:
        The path written. A stored rectification is written by the formats in `RECTIFICATION_FORMATS`; the others
        warn that they leave it out.

    Raises:
        ValueError: unknown format, an incomplete stored rectification (``opencv-yaml``), a ``colmap`` folder
            that holds other files, or a calibration that contradicts its grid (its import would be refused).
        OSError: the output cannot be written.
    """
    writer = _WRITERS.get(fmt)
    if writer is None:
        raise ValueError(f"unknown export format {fmt!r}; valid formats: {', '.join(EXPORT_FORMATS)}")
    out = Path(path)
    errors, _ = grid_problems(calib.grid, calib.ref_T_view, strict=True)  # what an import of it would refuse
    if errors:
        raise ValueError(f"{out}: not written: the calibration contradicts its grid, and its import would be "
                         f"refused: {'; '.join(errors)}")
    writer(calib, out)
    if calib.rectification is not None and fmt not in RECTIFICATION_FORMATS:
        logging.getLogger("lfgraph").warning(
            "%s: %s has no place for a rectification: the stored one is not written (an import of this file has "
            "none; `lfgraph rectify` computes it again; opencv-yaml and json keep it)", out, fmt)
    return out


def import_calibration(path: PathLike, fmt: str, grid: GridLike = None) -> Calibration:
    """Read a calibration written by another tool (see each format's module).

    Args:
        path: the file (for ``colmap`` the model folder; for ``middlebury`` and ``hci`` also the scene folder).
        fmt: one of `IMPORT_FORMATS`: ``opencv-yaml``, ``kalibr``, ``colmap``, ``json``, ``middlebury``, ``hci``.
        grid: the view grid, as a `ViewGrid` (its reference becomes the calibration's reference) or ``(rows, cols)``
            (the file's reference is kept); required for ``kalibr`` and for a ``colmap`` folder without the
            ``# lfgraph grid`` comment, optional (and then checked against the file) otherwise.

    Returns:
        The calibration, row-major views, poses relative to the reference view. Metrics are empty for every format
        but ``json``; the rectification is the file's for ``json`` and ``opencv-yaml`` (when it holds one), else
        None.

    Raises:
        ValueError: unknown format. `CalibrationFileError` (a ValueError) naming the file and the key: a missing
            file or key, a malformed or non-finite number, a matrix of the wrong shape or not a rotation, a grid
            whose shape or view count does not match the file, more than `MAX_IMPORT_VIEWS` views, a rectification
            that is incomplete or does not rectify the file's calibration (``opencv-yaml``).
    """
    reader = _READERS.get(fmt)
    if reader is None:
        raise ValueError(f"unknown import format {fmt!r}; valid formats: {', '.join(IMPORT_FORMATS)}")
    calib = reader(Path(path), grid)
    errors, _ = grid_problems(calib.grid, calib.ref_T_view, strict=True)  # the file's poses against its grid
    if errors:
        raise fail(path, "grid", "; ".join(errors))
    _warn_of_units(calib, path)
    return calib


SUSPECT_BASELINE_M = 5.0  # neighbouring views of an array farther apart than this: translations in mm read as m?


def _warn_of_units(calib: Calibration, path: PathLike) -> None:
    """A warning when the file's neighbouring views are `SUSPECT_BASELINE_M` or more apart: camera arrays are
    centimetres to a metre wide, and a file in millimetres read as metres gives baselines 1000x too long."""
    grid, centres = calib.grid, calib.ref_T_view[:, :3, 3]
    gaps = [float(np.linalg.norm(centres[a] - centres[b])) for a in range(grid.num_views) for b in grid.neighbours(a)]
    if gaps and float(np.median(gaps)) >= SUSPECT_BASELINE_M:
        logging.getLogger("lfgraph").warning(
            "%s: neighbouring views are %.4g m apart (median): are the file's translations in millimetres? lfgraph "
            "reads this format in metres", path, float(np.median(gaps)))


def input_paths(path: PathLike, fmt: str) -> tuple[Path, ...]:
    """The paths `import_calibration(path, fmt)` reads: ``path`` and, for a folder, the files in it that it reads.

    Raises:
        ValueError: unknown format.
    """
    if fmt not in _READERS:
        raise ValueError(f"unknown import format {fmt!r}; valid formats: {', '.join(IMPORT_FORMATS)}")
    source = Path(path)
    if fmt == "colmap":
        return (source, *(source / name for name in sorted(COLMAP_MODEL_FILES)))
    if fmt == "middlebury":
        return tuple(dict.fromkeys((source, in_folder(source, middlebury.CALIB_FILE))))
    if fmt == "hci":
        return tuple(dict.fromkeys((source, in_folder(source, hci.PARAMETERS_FILE))))
    return (source,)
