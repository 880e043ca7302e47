"""Shared helpers of the interop formats: errors that name the file and the key, number and array validation,
YAML loading, and the grid an import ends up with.

Grids on import: ``grid`` is a `ViewGrid`, a ``(rows, cols)`` pair or None. Its view count and shape must match
the file's (the error names the file and the key). A `ViewGrid` whose reference differs from the file's re-expresses
all poses relative to that view (refused when the file holds a rectification, which is tied to its reference);
a ``(rows, cols)`` pair keeps the file's reference. No import holds more than `MAX_IMPORT_VIEWS` views: a file
that declares more is refused before its views are read.
"""

from __future__ import annotations

import contextlib
import gc
import math
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import yaml

from lfgraph.core.calibration import (
    FILE_ROTATION_TOLERANCE,
    REFERENCE_POSE_TOLERANCE,
    Calibration,
    CalibrationFileError,
    nearest_rotation,
)
from lfgraph.core.camera import Intrinsics
from lfgraph.core.files import default_mode, input_problem
from lfgraph.core.geometry import invert_T, is_rotation, make_T
from lfgraph.core.grid import ViewGrid

MM_PER_M = 1000.0
HOMOGENEOUS_ROW_TOLERANCE = 1e-9  # the last row of a 4x4 transform must be [0, 0, 0, 1] to this
# Far beyond any camera array (the largest light-field rigs hold a few hundred views); a header asking for more is a
# typo or a hostile file, refused before anything is allocated per view.
MAX_IMPORT_VIEWS = 10_000

GridLike = ViewGrid | Sequence[int] | None
PathLike = str | os.PathLike

# libyaml's C parser when PyYAML was built with it (tens of times faster on large files), else the pure-Python one
_YAML_BASE_LOADER: type = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
_YAML_TEXT_LOADER: type = getattr(yaml, "CBaseLoader", yaml.BaseLoader)  # no implicit types: every scalar is text
T = TypeVar("T")


def fail(path: PathLike | None, key: str, problem: str) -> CalibrationFileError:
    """The `CalibrationFileError` of an import: ``path`` and ``key`` name where, ``problem`` what."""
    return CalibrationFileError(path, key, problem)


def read_text(path: Path) -> str:
    """The UTF-8 text of an input file; a missing, unreadable or special file (a FIFO, a device) is a
    `CalibrationFileError` naming it."""
    problem = input_problem(path)
    if problem:
        raise fail(path, "file", problem)
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise fail(path, "file", f"cannot be read ({exc})") from None


def in_folder(path: Path, filename: str) -> Path:
    """``path`` itself, or ``path / filename`` when ``path`` is a folder (a Middlebury or HCI scene)."""
    return path / filename if path.is_dir() else path


class _StrictYamlLoader(_YAML_BASE_LOADER):  # type: ignore[misc, valid-type]
    """PyYAML's safe loader, except that a key given twice in one mapping is an error (PyYAML keeps the last)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            if isinstance(key, list | dict):
                continue  # unhashable keys are never what a calibration file means; let PyYAML report them
            if key in seen:
                mark = key_node.start_mark
                raise yaml.constructor.ConstructorError(None, None, f"{key!r} appears twice", mark)
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def yaml_loader(name: str, constructors: dict[str, Any] | None = None) -> type:
    """A strict safe YAML loader class with extra tag ``constructors`` (``{tag: fn(loader, node)}``)."""
    cls = type(name, (_StrictYamlLoader,), {"yaml_constructors": dict(_StrictYamlLoader.yaml_constructors)})
    for tag, fn in (constructors or {}).items():
        cls.add_constructor(tag, fn)
    return cls


STRICT_YAML_LOADER = yaml_loader("StrictYamlLoader")


@contextlib.contextmanager
def _yaml_errors(path: PathLike) -> Iterator[None]:
    """Turn a YAML syntax error into `CalibrationFileError` naming the file and the line; pause the cyclic GC.

    Every object the parser allocates stays alive until it returns, so the collector's passes find nothing to free
    yet cost time proportional to all objects so far: a large file parsed superlinearly (5x slower for 3,600 views).
    Collection resumes afterwards.
    """
    collecting = gc.isenabled()
    gc.disable()
    try:
        yield
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}" if mark is not None else "file"
        problem = getattr(exc, "problem", None) or str(exc)
        raise fail(path, where, f"not valid YAML ({' '.join(str(problem).split())})") from None
    finally:
        if collecting:
            gc.enable()


def load_yaml(text: str, path: PathLike, loader: type = STRICT_YAML_LOADER) -> Any:
    """Parse YAML text into Python objects; a syntax error raises `CalibrationFileError` naming the file and line."""
    with _yaml_errors(path):
        return yaml.load(text, Loader=loader)  # noqa: S506 - loader is always a SafeLoader subclass


def compose_yaml(text: str, path: PathLike, convert: Callable[[yaml.Node | None], T]) -> T:
    """Parse YAML text into its node tree (libyaml when available) and return ``convert(root)``.

    For large files of a known layout: PyYAML's constructors and implicit typing, not its parser, are most of the
    cost of `load_yaml`, so the reader walks the nodes itself. Scalars stay text (no implicit typing; explicit tags
    such as ``!!opencv-matrix`` are kept). ``convert`` runs while the cyclic GC is paused and should return few
    containers, so that the node tree is freed before collection resumes.
    """
    with _yaml_errors(path):
        return convert(yaml.compose(text, Loader=_YAML_TEXT_LOADER))  # noqa: S506 - compose builds no objects


def finite(value: Any, path: PathLike, key: str) -> float:
    """A finite float from a number or numeric text; anything else raises naming the key."""
    if isinstance(value, bool):
        raise fail(path, key, f"must be a number, got {value!r}")
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise fail(path, key, f"must be a number, got {value!r}") from None
    if not math.isfinite(x):
        raise fail(path, key, f"must be finite, got {value!r}")
    return x


def whole(value: Any, path: PathLike, key: str, minimum: int = 1) -> int:
    """An integer >= ``minimum`` from an int, an integral float or text."""
    x = finite(value, path, key)
    if x != int(x) or x < minimum:
        raise fail(path, key, f"must be a whole number >= {minimum}, got {value!r}")
    return int(x)


def array(values: Any, shape: tuple[int, ...], path: PathLike, key: str) -> np.ndarray:
    """A finite float64 array of ``shape`` from nested lists or an array; raises naming the key.

    A vector may arrive as a row or a column (``1xN``, ``Nx1``): dimensions of length 1 are not compared.
    """
    want = "x".join(map(str, shape))
    if isinstance(values, np.ndarray) and values.dtype == np.float64 and bool(np.isfinite(values).all()):
        arr = values  # already numbers (a large file's matrices): skip the per-element checks below
    else:
        try:
            arr = np.array(values, dtype=object)
        except ValueError:
            raise fail(path, key, f"must be a {want} array of numbers") from None
    squeeze = tuple(d for d in arr.shape if d != 1)
    if arr.size != math.prod(shape) or squeeze != tuple(d for d in shape if d != 1):
        raise fail(path, key, f"must have shape {want}, got {'x'.join(map(str, arr.shape)) or 'a scalar'}")
    if arr is values:
        return np.array(arr, dtype=np.float64).reshape(shape)
    return np.array([finite(v, path, key) for v in arr.ravel()]).reshape(shape)


def intrinsics(path: PathLike, key: str, K: np.ndarray, dist: Sequence[float] | np.ndarray | None,  # noqa: N803
               lens: str = "radtan") -> Intrinsics:
    """`Intrinsics` from an OpenCV camera matrix ``K`` (3x3, px) and distortion coefficients of ``lens``; a bad value
    is a `CalibrationFileError` naming ``path`` and ``key``."""
    try:
        return Intrinsics.from_opencv(K, None if dist is None else np.asarray(dist, dtype=np.float64), lens)
    except ValueError as exc:
        raise fail(path, key, str(exc)) from None


def rotation(R: np.ndarray, path: PathLike, key: str) -> np.ndarray:  # noqa: N803
    """``R`` (3x3) checked to be a rotation matrix to a file's printed precision (`FILE_ROTATION_TOLERANCE`) and
    returned re-orthonormalised; a `CalibrationFileError` naming ``path`` and ``key`` otherwise."""
    if not is_rotation(R, FILE_ROTATION_TOLERANCE):
        raise fail(path, key, f"is not a rotation matrix (R^T R must be I to {FILE_ROTATION_TOLERANCE:g} and "
                              f"det R = +1)")
    return nearest_rotation(R)


def transform(T: np.ndarray, path: PathLike, key: str) -> np.ndarray:  # noqa: N803
    """Check a (4, 4) rigid transform read from a file."""
    if np.max(np.abs(T[3] - [0.0, 0.0, 0.0, 1.0])) > HOMOGENEOUS_ROW_TOLERANCE:
        raise fail(path, key, f"last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    return make_T(rotation(T[:3, :3], path, key), T[:3, 3])


def check_view_count(num_views: int, path: PathLike, key: str) -> None:
    """Refuse a file that declares more than `MAX_IMPORT_VIEWS` views, before any per-view work."""
    if num_views > MAX_IMPORT_VIEWS:
        raise fail(path, key, f"declares {num_views} views; lfgraph imports at most {MAX_IMPORT_VIEWS}")


def build(path: PathLike, key: str, grid: ViewGrid, image_size_px: tuple[int, int],
          views: Sequence[Intrinsics], ref_T_view: np.ndarray,  # noqa: N803
          view_image_sizes_px: Sequence[tuple[int, int]] | None = None) -> Calibration:
    """The `Calibration` an import read (poses in metres, relative to the reference; ``view_image_sizes_px`` each view's
    image size where the file gives one per view); what the constructor refuses is a `CalibrationFileError` naming
    ``path`` and ``key``."""
    try:
        return Calibration(grid, image_size_px, tuple(views), ref_T_view,
                           view_image_sizes_px=None if view_image_sizes_px is None else tuple(view_image_sizes_px))
    except ValueError as exc:
        raise fail(path, key, str(exc)) from None


def grid_dims(grid: GridLike) -> tuple[int, int, int | None] | None:
    """(rows, cols, reference or None) of a grid argument."""
    if grid is None:
        return None
    if isinstance(grid, ViewGrid):
        return grid.rows, grid.cols, grid.reference
    try:
        rows, cols = (int(x) for x in grid)
    except (TypeError, ValueError):
        raise ValueError(f"grid must be a ViewGrid or (rows, cols), got {grid!r}") from None
    ViewGrid(rows, cols)  # validates the dimensions
    return rows, cols, None


def required_grid(grid: GridLike, num_views: int, path: PathLike, key: str, reference: int) -> ViewGrid:
    """The grid of a file that does not store one: ``grid`` must be given and hold ``num_views`` views.

    The returned grid has the file's natural ``reference``; `fit_grid` then moves it to the one asked for.
    """
    check_view_count(num_views, path, key)
    dims = grid_dims(grid)
    if dims is None:
        raise fail(path, "grid", f"this format does not store the grid of its {num_views} views; give the grid "
                                 f"(rows x cols, e.g. --grid RxC)")
    rows, cols, _ = dims
    if rows * cols != num_views:
        raise fail(path, key, f"holds {num_views} views, but the {rows}x{cols} grid needs {rows * cols}")
    return ViewGrid(rows, cols, reference)


def fit_grid(calib: Calibration, grid: GridLike, path: PathLike, key: str) -> Calibration:
    """Check ``calib`` (as read) against the grid asked for; re-express it relative to that grid's reference."""
    dims = grid_dims(grid)
    if dims is None:
        return calib
    rows, cols, reference = dims
    if rows * cols != calib.num_views:
        raise fail(path, key, f"holds {calib.num_views} views, but the {rows}x{cols} grid needs {rows * cols}")
    if (rows, cols) != (calib.grid.rows, calib.grid.cols):
        raise fail(path, "grid", f"the file's grid is {calib.grid}, but {rows}x{cols} was asked for")
    if reference is None or reference == calib.grid.reference:
        return calib
    if calib.rectification is not None:
        raise fail(path, "rectification", f"is tied to reference view {calib.grid.reference} and cannot move to "
                                          f"view {reference}; import with the file's reference and rectify again")
    new_T_ref = invert_T(calib.ref_T_view[reference])  # noqa: N806 - new reference from old reference
    new_T_view = np.einsum("ij,vjk->vik", new_T_ref, calib.ref_T_view)  # noqa: N806
    new_T_view[reference] = np.eye(4)  # exactly, not to rounding
    return calib.replace(grid=ViewGrid(rows, cols, reference), ref_T_view=new_T_view)


def check_reference_pose(view_T_ref: np.ndarray, path: PathLike, key: str) -> None:  # noqa: N803
    """A file's pose of the reference view (``view_T_ref``, 4x4, m) must be the identity to 1e-9; a
    `CalibrationFileError` naming ``path`` and ``key`` otherwise."""
    if np.max(np.abs(view_T_ref - np.eye(4))) > REFERENCE_POSE_TOLERANCE:
        raise fail(path, key, "belongs to the reference view, so it must be the identity")


def num(x: float) -> str:
    """Shortest text that reads back as exactly ``x``."""
    return repr(float(x))


def write_folder(final: Path, files: dict[str, str], ours: Callable[[str], bool], what: str) -> None:
    """Write ``files`` (name -> text) as the folder ``final``, all at once: a temporary sibling folder renamed into
    place, so the folder never appears half-written. An existing folder is replaced only when every file in it is
    one of ``ours`` (names this export writes); ``what`` names the export in errors.

    Raises:
        ValueError: ``final`` is a file, or a folder holding other files.
    """
    if final.exists() and not final.is_dir():
        raise ValueError(f"{final}: {what} is a folder, but a file of that name exists")
    if final.is_dir():
        others = sorted(p.name for p in final.iterdir() if not ours(p.name))
        if others:
            raise ValueError(f"{final}: the folder holds files that are not part of {what} "
                             f"({', '.join(others[:5])}{', ...' if len(others) > 5 else ''}); refusing to replace it")
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".tmp", dir=final.parent))
    old: Path | None = None
    try:
        for name, text in files.items():
            (tmp / name).write_text(text, encoding="utf-8")
        # mkdtemp makes a 0700 folder; the export gets the mode mkdir would give (or the replaced folder's)
        os.chmod(tmp, final.stat().st_mode & 0o777 if final.is_dir() else default_mode(0o777))
        if final.is_dir():
            old = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".old", dir=final.parent))
            os.replace(final, old)  # onto an empty folder: allowed by rename(2)
            try:
                os.replace(tmp, final)
            except OSError:
                os.replace(old, final)
                old = None
                raise
        else:
            os.replace(tmp, final)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
        if old is not None and old.exists():
            shutil.rmtree(old, ignore_errors=True)
