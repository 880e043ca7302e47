"""A calibrated array (`Calibration`) and its JSON file ``calibration.json`` (format in docs/architecture.md)."""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lfgraph.core.camera import Intrinsics
from lfgraph.core.files import input_problem, write_text_atomic
from lfgraph.core.geometry import invert_T, is_rotation, make_T
from lfgraph.core.grid import ViewGrid, free_grid
from lfgraph.core.sigmas import Sigmas
from lfgraph.lenses import DEFAULT_LENS, lens_model, lens_names

FORMAT_NAME = "lfgraph.calibration"  # the file format's name (not a module path: files written since 0.1 carry it)
FORMAT_VERSION = 1
REFERENCE_POSE_TOLERANCE = 1e-9  # the reference view's pose must be the identity to this (rad, m)
# max |R^T R - I| entry of a rotation read from a file: one printed to 6 decimals (HALCON and many tools write them
# so) is off by up to ~3e-6; anything within this is a rotation to the file's precision (re-orthonormalised on load)
FILE_ROTATION_TOLERANCE = 1e-4
EXACT_ROTATION_TOLERANCE = 1e-12  # orthonormal to round-off: kept as stored
DEFAULT_METRICS: dict[str, Any] = {"e_mono_px": None, "e_pnp_px": None, "rig_rms_px": None}


class CalibrationFileError(ValueError):
    """A calibration file that cannot be read; the message names the file and the field."""

    def __init__(self, path: str | os.PathLike | None, field: str, problem: str) -> None:
        self.path = None if path is None else str(path)
        self.field = field
        where = f"{self.path}: " if self.path else ""
        super().__init__(f"{where}{field}: {problem}")


def image_size_checked(size: object, name: str) -> tuple[int, int]:
    """``size`` as (width, height) in whole, positive pixels; ValueError naming ``name`` otherwise (a fraction is
    refused, not truncated)."""
    try:
        w, h = size  # type: ignore[misc]
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be (width, height) in whole pixels, got {size!r}") from None
    if not all(isinstance(x, int | np.integer) and not isinstance(x, bool) for x in (w, h)):
        raise ValueError(f"{name} must be (width, height) in whole pixels, got {size!r}")
    if w <= 0 or h <= 0:
        raise ValueError(f"{name} must be positive (width, height), got {size!r}")
    return int(w), int(h)


@dataclass(frozen=True)
class Calibration:
    """Per-view intrinsics and poses of a camera array.

    Attributes:
        grid: the view grid and its reference view.
        image_size_px: (width, height) of every view in pixels.
        intrinsics: one `Intrinsics` per view, row-major.
        ref_T_view: (V, 4, 4) pose of each view in the reference view's frame (metres); identity for the reference.
        rectification: the stored rectification (see lfgraph.rectification.rectify), or None.
        metrics: figures of merit (``e_mono_px``, ``e_pnp_px``, ``rig_rms_px``, sigmas, ...), JSON-serialisable.
        view_image_sizes_px: (V,) (width, height) per view for a rig of mixed image sizes; None when every view
            has ``image_size_px`` (see `image_size`).
    """

    grid: ViewGrid
    image_size_px: tuple[int, int]
    intrinsics: tuple[Intrinsics, ...]
    ref_T_view: np.ndarray
    rectification: Mapping[str, Any] | None = None
    metrics: Mapping[str, Any] | None = None
    view_image_sizes_px: tuple[tuple[int, int], ...] | None = None

    def image_size(self, view: int) -> tuple[int, int]:
        """(width, height) of one view's images; ValueError for a view the grid does not have (-1 is no view)."""
        if isinstance(view, bool) or not isinstance(view, int | np.integer):
            raise TypeError(f"image_size: view must be a view index, got {view!r}")
        self.grid.position(int(view))  # ValueError naming the grid's range
        return self.image_size_px if self.view_image_sizes_px is None else self.view_image_sizes_px[view]

    @property
    def image_sizes(self) -> tuple[tuple[int, int], ...]:
        """(width, height) of every view's images, in view order."""
        return tuple(self.image_size(v) for v in range(self.grid.num_views))

    def __post_init__(self) -> None:
        n = self.grid.num_views
        object.__setattr__(self, "intrinsics", tuple(self.intrinsics))
        if len(self.intrinsics) != n:
            raise ValueError(f"a {self.grid} grid needs {n} intrinsics, got {len(self.intrinsics)}")
        poses = np.asarray(self.ref_T_view, dtype=np.float64)
        if poses.shape != (n, 4, 4):
            raise ValueError(f"ref_T_view must have shape ({n}, 4, 4), got {poses.shape}")
        if not np.all(np.isfinite(poses)):
            raise ValueError("ref_T_view contains NaN or infinity")
        for v in range(n):
            if not is_rotation(poses[v, :3, :3]):
                raise ValueError(f"ref_T_view[{v}] does not hold a rotation matrix")
        poses = poses.copy()
        poses.setflags(write=False)
        object.__setattr__(self, "ref_T_view", poses)
        if self.grid.is_free:  # a free arrangement's neighbours are its poses' (`lfgraph.core.grid.free_grid`)
            object.__setattr__(self, "grid", free_grid(poses, self.grid.reference, self.grid.rows))
        w, h = image_size_checked(self.image_size_px, "image_size_px")
        object.__setattr__(self, "image_size_px", (w, h))
        if self.view_image_sizes_px is not None:
            sizes = tuple(image_size_checked(s, "view_image_sizes_px") for s in self.view_image_sizes_px)
            if len(sizes) != n:
                raise ValueError(f"view_image_sizes_px must hold {n} (width, height), got {self.view_image_sizes_px}")
            object.__setattr__(self, "view_image_sizes_px", None if set(sizes) == {(w, h)} else sizes)
        object.__setattr__(self, "metrics", {**DEFAULT_METRICS, **dict(self.metrics or {})})

    @property
    def num_views(self) -> int:
        """Number of views of the array (rows x cols)."""
        return self.grid.num_views

    @property
    def lenses(self) -> tuple[str, ...]:
        """Each view's lens model."""
        return tuple(i.lens for i in self.intrinsics)

    @property
    def sigmas(self) -> Sigmas | None:
        """Each view's stored posterior 1-sigma (``metrics["sigmas"]``, `Sigmas.from_metrics`: what calibrate and
        calibrate-scene write, also calibrate-scene's older ``{"views": [...]}``), or None where absent, short or
        not finite."""
        return Sigmas.from_metrics((self.metrics or {}).get("sigmas"), self.num_views)

    def view_T_ref(self, view: int) -> np.ndarray:  # noqa: N802
        """(4, 4) OpenCV extrinsics of a view relative to the reference: ``x_view = R x_ref + t``."""
        return invert_T(self.ref_T_view[view])

    def replace(self, **changes: Any) -> Calibration:
        """A copy with the given fields changed (`dataclasses.replace`, validated again)."""
        return dataclasses.replace(self, **changes)

    def with_reference(self, reference: int) -> Calibration:
        """The same array expressed relative to another reference view (index ``reference``); the stored
        rectification, which belongs to the old reference, is dropped."""
        if not (isinstance(reference, int | np.integer) and 0 <= reference < self.num_views):
            raise ValueError(f"reference must be a view index from 0 to {self.num_views - 1}, got {reference!r}")
        poses = np.linalg.inv(self.ref_T_view[reference])[None] @ self.ref_T_view
        poses[reference] = np.eye(4)
        return self.replace(grid=dataclasses.replace(self.grid, reference=int(reference)), ref_T_view=poses,
                            rectification=None)

    # ------------------------------------------------------------------------------------------ JSON
    def to_dict(self) -> dict[str, Any]:
        """The calibration as the JSON-ready dict of ``calibration.json`` (format, version, grid, image size, one
        entry per view with K, lens, distortion and ``R/t_view_from_ref``, the rectification and the metrics)."""
        views = []
        for v in range(self.num_views):
            r, c = self.grid.position(v)
            intr = self.intrinsics[v]
            view_T_ref = self.view_T_ref(v)  # noqa: N806
            views.append({
                "index": v, "row": r, "col": c,
                "K": intr.K.tolist(),
                "lens": intr.lens,
                "distortion": intr.distortion,
                **({"image_size_px": list(self.image_size(v))} if self.image_size(v) != self.image_size_px else {}),
                "R_view_from_ref": view_T_ref[:3, :3].tolist(),
                "t_view_from_ref_m": view_T_ref[:3, 3].tolist(),
            })
        return {
            "format": FORMAT_NAME, "version": FORMAT_VERSION,
            "grid": self.grid.as_dict(),
            "image_size_px": list(self.image_size_px),
            "views": views,
            "rectification": None if self.rectification is None else dict(self.rectification),
            "metrics": dict(self.metrics or {}),
        }

    def summary_dict(self) -> dict[str, Any]:
        """Grid, image size and per-view parameters (positions in mm and rotation angles in degrees relative to the
        reference view) with the stored metrics: what ``lfgraph info --json`` prints."""
        from lfgraph.core.geometry import rotation_angle_deg

        views = []
        for v, intr in enumerate(self.intrinsics):
            views.append({"index": v, "name": self.grid.name(v), "fx_px": intr.fx, "fy_px": intr.fy, "cx_px": intr.cx,
                          "cy_px": intr.cy, "lens": intr.lens, **intr.distortion,
                          "image_size_px": list(self.image_size(v)),
                          "position_mm": [float(x) for x in 1e3 * self.ref_T_view[v, :3, 3]],
                          "rotation_deg": float(rotation_angle_deg(self.ref_T_view[v, :3, :3]))})
        return {"grid": self.grid.as_dict(),
                "image_size_px": list(self.image_size_px), "views": views,
                "rectification": self.rectification is not None, "metrics": dict(self.metrics or {})}

    def to_json(self) -> str:
        """`to_dict` as JSON text; a non-finite number is a ValueError (JSON has none)."""
        try:
            return json.dumps(self.to_dict(), indent=1, allow_nan=False) + "\n"
        except ValueError as exc:
            raise ValueError(f"calibration holds a non-finite number and cannot be saved: {exc}") from exc

    def save(self, path: str | os.PathLike) -> None:
        """Write ``calibration.json`` atomically (UTF-8)."""
        write_text_atomic(path, self.to_json())

    @classmethod
    def from_dict(cls, data: Any, path: str | os.PathLike | None = None) -> Calibration:
        """Validate and build from parsed JSON; every problem raises `CalibrationFileError` naming the field."""
        return _parse(data, path)

    @classmethod
    def load(cls, path: str | os.PathLike) -> Calibration:
        """Read a ``calibration.json``.

        Raises:
            CalibrationFileError: unreadable file, bad JSON, wrong format or version, NaN, a non-rotation matrix,
                a view count that does not match the grid, ... — the message names the file and the field.
        """
        p = Path(path)
        problem = input_problem(p)
        if problem:
            raise CalibrationFileError(p, "file", problem)
        try:
            text = p.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise CalibrationFileError(p, "file", "does not exist") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise CalibrationFileError(p, "file", f"cannot be read ({exc})") from None

        def reject_constant(name: str) -> float:
            raise CalibrationFileError(p, "JSON", f"non-finite number {name} is not allowed")

        try:
            data = json.loads(text, parse_constant=reject_constant)
        except json.JSONDecodeError as exc:
            raise CalibrationFileError(p, "JSON", f"not valid JSON (line {exc.lineno}, column {exc.colno}: "
                                                  f"{exc.msg})") from None
        except RecursionError:
            raise CalibrationFileError(p, "JSON", "is nested too deeply to be a calibration") from None
        return _parse(data, p)


class _Reader:
    """Field checks of one calibration.json: every failure a `CalibrationFileError` naming the file and field."""

    def __init__(self, path: str | os.PathLike | None):
        self.path = path

    def fail(self, field: str, problem: str) -> CalibrationFileError:
        return CalibrationFileError(self.path, field, problem)

    def get(self, obj: Any, key: str, where: str) -> Any:
        if not isinstance(obj, dict):
            raise self.fail(where or "top level", f"must be a JSON object, got {type(obj).__name__}")
        if key not in obj:
            raise self.fail(f"{where}.{key}" if where else key, "is missing")
        return obj[key]

    def number(self, x: Any, field: str) -> float:
        if isinstance(x, bool) or not isinstance(x, int | float):
            raise self.fail(field, f"must be a number, got {x!r}")
        try:
            value = float(x)
        except OverflowError:  # an integer too large for a float (JSON allows any number of digits)
            raise self.fail(field, f"is out of range ({len(str(x))}-digit number)") from None
        if not math.isfinite(value):
            raise self.fail(field, f"must be finite, got {x}")
        return value

    def matrix(self, x: Any, shape: tuple[int, ...], field: str) -> np.ndarray:
        try:
            arr = np.array(x, dtype=object)
        except ValueError:
            raise self.fail(field, f"must be a {'x'.join(map(str, shape))} array of numbers") from None
        if arr.shape != shape:
            raise self.fail(field, f"must have shape {'x'.join(map(str, shape))}, got {list(arr.shape)}")
        return np.array([self.number(v, field) for v in arr.ravel()]).reshape(shape)

    def size(self, value: Any, field: str) -> tuple[int, int]:
        if (not isinstance(value, list) or len(value) != 2
                or not all(isinstance(x, int) and not isinstance(x, bool) and x > 0 for x in value)):
            raise self.fail(field, f"must be [width, height] in positive whole pixels, got {value!r}")
        return value[0], value[1]

    def grid(self, data: Any) -> ViewGrid:
        g = self.get(data, "grid", "")
        dims = {}
        for key in ("rows", "cols", "reference"):
            val = self.get(g, key, "grid")
            if isinstance(val, bool) or not isinstance(val, int) or val < 0:
                raise self.fail(f"grid.{key}", f"must be a non-negative integer, got {val!r}")
            dims[key] = val
        arrangement = g.get("arrangement", "grid")  # a free arrangement's links follow from the poses
        try:
            return ViewGrid(dims["rows"], dims["cols"], dims["reference"], arrangement)
        except ValueError as exc:
            raise self.fail("grid", str(exc)) from None

    def view(self, view: Any, i: int, grid: ViewGrid,
             size: tuple[int, int]) -> tuple[Intrinsics, tuple[int, int], np.ndarray]:
        """View ``i``: its intrinsics, image size and ``ref_T_view``."""
        w = f"views[{i}]"
        index = self.get(view, "index", w)
        if index != i:
            raise self.fail(f"{w}.index", f"must be {i} (views are stored row-major), got {index!r}")
        r, c = grid.position(i)
        for key, expected in (("row", r), ("col", c)):
            if key in view and view[key] != expected:
                raise self.fail(f"{w}.{key}", f"must be {expected} for view {i} of a {grid} grid, got {view[key]!r}")
        K = self.matrix(self.get(view, "K", w), (3, 3), f"{w}.K")  # noqa: N806
        if K[0, 1] != 0 or K[1, 0] != 0 or np.any(K[2] != [0, 0, 1]) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise self.fail(f"{w}.K", f"must be [[fx,0,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0, got {K.tolist()}")
        lens = view.get("lens", DEFAULT_LENS)
        if not isinstance(lens, str) or lens not in lens_names():  # the registry now: a model registered later too
            raise self.fail(f"{w}.lens", f"must be one of {', '.join(lens_names())}, got {lens!r}")
        keys = lens_model(lens).coefficients
        dist = self.get(view, "distortion", w)
        coeffs = {k: self.number(self.get(dist, k, f"{w}.distortion"), f"{w}.distortion.{k}") for k in keys}
        extra = sorted(set(dist) - set(keys))
        if extra:
            raise self.fail(f"{w}.distortion", f"a {lens} lens has {', '.join(keys)}, not "
                                               f"{', '.join(map(str, extra))}")
        try:
            intrinsics = Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], **coeffs, lens=lens)
        except ValueError as exc:
            raise self.fail(f"{w}.distortion", str(exc)) from None
        own = self.size(view.get("image_size_px", list(size)), f"{w}.image_size_px")
        R = self.matrix(self.get(view, "R_view_from_ref", w), (3, 3), f"{w}.R_view_from_ref")  # noqa: N806
        if not is_rotation(R, FILE_ROTATION_TOLERANCE):
            raise self.fail(f"{w}.R_view_from_ref", f"is not a rotation matrix (R^T R must be I to "
                                                    f"{FILE_ROTATION_TOLERANCE:g} and det R = +1)")
        R = nearest_rotation(R)  # noqa: N806
        t = self.matrix(self.get(view, "t_view_from_ref_m", w), (3,), f"{w}.t_view_from_ref_m")
        return intrinsics, own, invert_T(make_T(R, t))


def nearest_rotation(R: np.ndarray) -> np.ndarray:  # noqa: N803
    """The rotation nearest to ``R`` (Frobenius norm; SVD: U V^T), for a matrix that is one to a file's printed
    precision (checked before: orthonormal to `FILE_ROTATION_TOLERANCE`, determinant +1). A matrix that is a
    rotation to round-off (`EXACT_ROTATION_TOLERANCE`: every file lfgraph writes) is returned as it is, so a
    calibration saved and loaded again is the same to the bit."""
    R = np.asarray(R, dtype=np.float64)  # noqa: N806
    if is_rotation(R, EXACT_ROTATION_TOLERANCE):
        return R
    U, _, Vt = np.linalg.svd(R)  # noqa: N806
    return U @ Vt


def _parse(data: Any, path: str | os.PathLike | None) -> Calibration:
    read = _Reader(path)
    fmt = read.get(data, "format", "")
    if fmt != FORMAT_NAME:
        raise read.fail("format", f"must be {FORMAT_NAME!r}, got {fmt!r}")
    version = read.get(data, "version", "")
    if version != FORMAT_VERSION:
        raise read.fail("version", f"unknown version {version!r}; this lfgraph reads version {FORMAT_VERSION}")
    grid = read.grid(data)
    size = read.size(read.get(data, "image_size_px", ""), "image_size_px")
    views = read.get(data, "views", "")
    if not isinstance(views, list):
        raise read.fail("views", f"must be a list, got {type(views).__name__}")
    if len(views) != grid.num_views:
        raise read.fail("views", f"has {len(views)} entries but the {grid} grid needs {grid.num_views}")
    intrinsics, sizes, poses = zip(*(read.view(view, i, grid, size) for i, view in enumerate(views)), strict=True)
    if np.max(np.abs(poses[grid.reference] - np.eye(4))) > REFERENCE_POSE_TOLERANCE:
        raise read.fail(f"views[{grid.reference}]", "is the reference view, so its R_view_from_ref must be the "
                                                     "identity and its t_view_from_ref_m zero")
    rect = data.get("rectification")
    if rect is not None and not isinstance(rect, dict):
        raise read.fail("rectification", f"must be an object or null, got {type(rect).__name__}")
    metrics = data.get("metrics", {})
    if metrics is None:
        metrics = {}
    if not isinstance(metrics, dict):
        raise read.fail("metrics", f"must be an object, got {type(metrics).__name__}")
    return Calibration(grid, size, tuple(intrinsics), np.stack(poses), rect, metrics, tuple(sizes))
