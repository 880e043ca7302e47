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
from dataclasses import dataclass
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
    "FileFormat",
    "KALIBR_DISTORTION_MODELS",
    "MAX_IMPORT_VIEWS",
    "MM_PER_M",
    "FILE_FORMATS",
    "RECTIFICATION_FORMATS",
    "export_calibration",
    "export_formats",
    "file_format",
    "import_calibration",
    "import_formats",
    "input_paths",
    "register_format",
]

@dataclass(frozen=True)
class FileFormat:
    """One format: its name, its writer ``write(calib, path)`` and reader ``read(path, grid) -> Calibration`` (either
    may be None: export-only or import-only), whether an export is one file (else a folder), whether it keeps a
    stored rectification, and ``inputs(path)``: every path an import of ``path`` reads (None: ``path`` alone)."""

    name: str
    write: Callable[[Calibration, Path], None] | None = None
    read: Callable[[Path, GridLike], Calibration] | None = None
    one_file: bool = True
    rectification: bool = False
    inputs: Callable[[Path], tuple[Path, ...]] | None = None


_FORMATS: dict[str, FileFormat] = {}


def register_format(fmt: FileFormat) -> None:
    """Make a format known to `export_calibration`, `import_calibration` and ``lfgraph export/import`` by its name (a
    new name only)."""
    if fmt.name in _FORMATS:
        raise ValueError(f"a format named {fmt.name!r} is registered already")
    if fmt.write is None and fmt.read is None:
        raise ValueError(f"format {fmt.name!r}: give a writer, a reader or both")
    _FORMATS[fmt.name] = fmt


for _fmt in (FileFormat("opencv-yaml", opencv_yaml.write, opencv_yaml.read, rectification=True),  # one line each
             FileFormat("kalibr", kalibr.write, kalibr.read),
             FileFormat("colmap", colmap.write, colmap.read, one_file=False,
                        inputs=lambda p: (p, *(p / name for name in sorted(COLMAP_MODEL_FILES)))),
             FileFormat("json", json_format.write, json_format.read, rectification=True),
             # ros: a stored rectification as each camera_info's R and P (not read back)
             FileFormat("ros", ros.write, None, one_file=False, rectification=True),
             FileFormat("mrcal", mrcal.write, None, one_file=False),
             FileFormat("middlebury", None, middlebury.read,
                        inputs=lambda p: tuple(dict.fromkeys((p, in_folder(p, middlebury.CALIB_FILE))))),
             FileFormat("hci", None, hci.read,
                        inputs=lambda p: tuple(dict.fromkeys((p, in_folder(p, hci.PARAMETERS_FILE)))))):
    register_format(_fmt)


def export_formats() -> tuple[str, ...]:
    """The names of every registered format that can be written."""
    return tuple(name for name, f in _FORMATS.items() if f.write is not None)


def import_formats() -> tuple[str, ...]:
    """The names of every registered format that can be read."""
    return tuple(name for name, f in _FORMATS.items() if f.read is not None)


def file_format(name: str) -> FileFormat | None:
    """The registered format called ``name`` (None: unknown)."""
    return _FORMATS.get(name)


EXPORT_FORMATS: tuple[str, ...] = export_formats()  # the built-in ones (`export_formats` also sees registrations)
IMPORT_FORMATS: tuple[str, ...] = import_formats()
FILE_FORMATS: tuple[str, ...] = tuple(n for n in EXPORT_FORMATS if _FORMATS[n].one_file)  # colmap, ros, mrcal: folders
# exports that write a stored rectification; the others have no place for one, and an export to them says so
RECTIFICATION_FORMATS: tuple[str, ...] = tuple(n for n in EXPORT_FORMATS if _FORMATS[n].rectification)


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
    spec = _FORMATS.get(fmt)
    if spec is None or spec.write is None:
        raise ValueError(f"unknown export format {fmt!r}; valid formats: {', '.join(export_formats())}")
    out = Path(path)
    errors, _ = grid_problems(calib.grid, calib.ref_T_view, strict=True)  # what an import of it would refuse
    if errors:
        raise ValueError(f"{out}: not written: the calibration contradicts its grid, and its import would be "
                         f"refused: {'; '.join(errors)}")
    spec.write(calib, out)
    if calib.rectification is not None and not spec.rectification:
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
    spec = _FORMATS.get(fmt)
    if spec is None or spec.read is None:
        raise ValueError(f"unknown import format {fmt!r}; valid formats: {', '.join(import_formats())}")
    calib = spec.read(Path(path), grid)
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
    spec = _FORMATS.get(fmt)
    if spec is None or spec.read is None:
        raise ValueError(f"unknown import format {fmt!r}; valid formats: {', '.join(import_formats())}")
    return (Path(path),) if spec.inputs is None else spec.inputs(Path(path))
