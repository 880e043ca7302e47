"""Input layouts of camera-array captures, auto-detected, loaded lazily one frame at a time.

Layouts (views row-major):
- ``folders``: ``DIR/<frame>/r{row:02d}_c{col:02d}.<ext>``, frames in natural name order; a single folder holding
  ``rRR_cCC`` files is one frame.
- ``mosaic``: ``DIR/<frame>.<ext>``, one image per frame with the views tiled row-major.
- ``hci``: ``input_Cam000.<ext>`` ... (row-major index) in one folder (one frame) or in per-frame folders.
- ``pairs``: ``left<id>.<ext>`` / ``right<id>.<ext>`` stereo sets (OpenCV's sample), a 1x2 grid, frames by ``<id>``.
- ``middlebury``: Middlebury 2014 scene folders, a 1x2 grid: ``im0.<ext>`` (left) and ``im1.<ext>`` (right) of one
  scene folder (one frame), or of each scene folder in ``DIR`` (one frame per folder); ``calib.txt`` beside them
  (``lfgraph import --from middlebury``) is what auto-detection looks for; the scene's other files (``im1E``,
  ``mask0nocc``, ``disp0GT``, ...) are not read.
- ``views``: ``DIR/<view>/<name><N>.<ext>``, one folder per view (folders in natural name order = row-major views,
  e.g. ``left/ middle/ right/``), frames matched by the number ``N`` at the end of each file name (``left7.jpg`` and
  ``right7.jpg`` are frame 7); BoofCV's and many rigs' own layout.
- ``video``: ``DIR/<name>.<ext>``, one video per view, views in natural name order (``cam_0.mp4``, ``cam_1.mp4``,
  ... row-major); frame f is the f-th decoded frame of every video; the capture has as many frames as the shortest
  video (`CaptureSet.notes` says so when the lengths differ).

``open_capture`` checks names and presence of every file and the size of the first frame's images; every image's
size and readability are checked when its frame is loaded. A frame that lacks a view's image is an error unless
``missing="unseen"``: that view-frame then has no file (None in `CaptureSet.files`), loads as a black image and
counts as "board not seen".
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from lfgraph.core.errors import CaptureError
from lfgraph.core.files import atomic_path
from lfgraph.core.grid import ViewGrid
from lfgraph.io.layouts import (  # noqa: F401  (IMAGE_EXTENSIONS, VIDEO_EXTENSIONS: re-exported)
    IMAGE_EXTENSIONS,
    VIDEO_EXTENSIONS,
    detect_layout,
    frame_files,
    video_files,
)
from lfgraph.io.video import read_video_frame, video_info

LAYOUTS = ("auto", "folders", "mosaic", "hci", "pairs", "middlebury", "views", "video")
MISSING_VIEW = ("error", "unseen")  # what a frame without one of its view images is
def _read(path: Path, grayscale: bool) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE if grayscale else cv2.IMREAD_COLOR)
    if img is None:
        raise CaptureError(f"{path}: cannot read this image (missing, unreadable or not an image)")
    return img


def split_mosaic(image: np.ndarray, grid: ViewGrid, path: str | os.PathLike = "mosaic") -> np.ndarray:
    """(rows*H, cols*W[, 3]) mosaic -> (V, H, W[, 3]) views, row-major."""
    h_all, w_all = image.shape[:2]
    if h_all % grid.rows or w_all % grid.cols:
        raise CaptureError(f"{path}: a {w_all}x{h_all} mosaic does not divide into a {grid} grid of equal views")
    h, w = h_all // grid.rows, w_all // grid.cols
    tiles = image.reshape(grid.rows, h, grid.cols, w, *image.shape[2:]).swapaxes(1, 2)
    return tiles.reshape(grid.num_views, h, w, *image.shape[2:]).copy()


def tile_mosaic(images: np.ndarray, grid: ViewGrid) -> np.ndarray:
    """(V, H, W[, 3]) views -> (rows*H, cols*W[, 3]) mosaic, row-major."""
    images = np.asarray(images)
    if images.shape[0] != grid.num_views:
        raise ValueError(f"a {grid} mosaic needs {grid.num_views} views, got {images.shape[0]}")
    v, h, w = images.shape[:3]
    tiles = images.reshape(grid.rows, grid.cols, h, w, *images.shape[3:]).swapaxes(1, 2)
    return tiles.reshape(grid.rows * h, grid.cols * w, *images.shape[3:])


MIN_IMAGE_SIDE_PX = 8  # smaller "views" cannot hold a board (OpenCV's detector asserts on them)


@dataclass(frozen=True)
class CaptureSet:
    """A capture on disk: paths only, images are read one frame at a time.

    Attributes:
        root: the input folder.
        layout: one of `LAYOUTS` but ``auto``.
        grid: the view grid.
        frame_names: one name per frame, in order.
        files: per frame, the view files in row-major order (one file for a mosaic; the view's video for
            ``video``); None for a view image missing from its frame (only with ``missing="unseen"``).
        image_size_px: (width, height) of the first view, from the first frame.
        notes: what the user should know about the input (videos of different lengths, missing view images).
        view_image_sizes_px: (V,) (width, height) per view for a rig of mixed image sizes (from each view's first
            image); None when every view is ``image_size_px``.
    """

    root: Path
    layout: str
    grid: ViewGrid
    frame_names: tuple[str, ...]
    files: tuple[tuple[Path | None, ...], ...]
    image_size_px: tuple[int, int]
    notes: tuple[str, ...] = ()
    view_image_sizes_px: tuple[tuple[int, int], ...] | None = None

    def __post_init__(self) -> None:
        if self.view_image_sizes_px is not None and len(set(self.view_image_sizes_px)) == 1:
            object.__setattr__(self, "view_image_sizes_px", None)
        for v in range(self.grid.num_views):
            w, h = self.image_size(v)
            if min(w, h) < MIN_IMAGE_SIDE_PX:
                first = next((p for views in self.files for p in views if p is not None), self.root)
                raise CaptureError(f"{first}: the views are {w}x{h} px; a view needs at least {MIN_IMAGE_SIDE_PX} px "
                                   f"on each side to show a board or a scene")

    def image_size(self, view: int) -> tuple[int, int]:
        """(width, height) of one view's images, px."""
        return self.image_size_px if self.view_image_sizes_px is None else self.view_image_sizes_px[view]

    @property
    def image_sizes(self) -> tuple[tuple[int, int], ...]:
        """(V,) (width, height) of every view, px."""
        return tuple(self.image_size(v) for v in range(self.grid.num_views))

    def require_one_size(self, what: str) -> None:
        """Refuse a rig of mixed image sizes for work that needs (V, H, W) frames (tracking), naming the sizes."""
        if self.view_image_sizes_px is not None:
            kinds = ", ".join(f"{self.grid.name(v)} {w}x{h}" for v, (w, h) in enumerate(self.view_image_sizes_px))
            raise CaptureError(f"{self.root}: the views have different image sizes ({kinds}); {what} needs views of "
                               f"one size (calibrate, rectify and refine take mixed rigs)")

    def __len__(self) -> int:
        return len(self.frame_names)

    def frames(self, limit: int | None = None, grayscale: bool = True) -> Iterator[np.ndarray]:
        """Each frame's (V, H, W) images in order, loaded lazily (at most ``limit`` frames, a whole number >= 1)."""
        if limit is not None and (isinstance(limit, bool) or not isinstance(limit, int | np.integer) or limit < 1):
            raise ValueError(f"frames(limit={limit!r}): the limit must be a whole number >= 1, or None for all frames")
        n = len(self) if limit is None else min(len(self), limit)
        for f in range(n):
            yield self.load_frame(f, grayscale)

    def all_paths(self) -> list[Path]:
        """Every file the capture reads (missing views left out)."""
        return [p for f in range(len(self)) for p in self.paths(f) if p is not None]

    def paths(self, frame: int) -> tuple[Path, ...]:
        """The image files of frame ``frame``, one per view (a mosaic: one file; None where a view's image is
        missing)."""
        return self.files[frame]

    def load_frame(self, frame: int, grayscale: bool = True) -> np.ndarray | list[np.ndarray]:
        """(V, H, W) uint8 grayscale (or (V, H, W, 3) BGR) images of one frame; checks every size. A rig of mixed
        image sizes (`view_image_sizes_px`) gives a list of V arrays, each its view's size."""
        if self.layout == "mosaic":
            path = self.files[frame][0]
            views = split_mosaic(_read(path, grayscale), self.grid, path)
            h, w = views.shape[1:3]
            if (w, h) != self.image_size_px:
                raise CaptureError(f"{path}: views are {w}x{h} px but the first frame's are "
                                   f"{self.image_size_px[0]}x{self.image_size_px[1]}")
            return views
        views = [self.load_view(frame, v, grayscale) for v in range(self.grid.num_views)]
        return views if self.view_image_sizes_px is not None else np.stack(views)

    def is_missing(self, frame: int, view: int) -> bool:
        """The frame has no image of this view (``missing="unseen"``): its board counts as not seen."""
        return self.layout != "mosaic" and self.files[frame][view] is None

    def load_view(self, frame: int, view: int, grayscale: bool = True) -> np.ndarray:
        """One view of one frame, (H, W) or (H, W, 3); black for a missing view image (``missing="unseen"``)."""
        if self.layout == "mosaic":
            return self.load_frame(frame, grayscale)[view]
        path = self.files[frame][view]
        w, h = self.image_size(view)
        if path is None:
            return np.zeros((h, w) if grayscale else (h, w, 3), np.uint8)
        if self.layout == "video":
            if not 0 <= frame < len(self):
                raise IndexError(f"frame {frame} out of range 0..{len(self) - 1}")
            img = read_video_frame(path, frame, grayscale)
        else:
            img = _read(path, grayscale)
        h, w = img.shape[:2]
        if (w, h) != self.image_size(view):
            what = f"frame {frame} is" if self.layout == "video" else "image is"
            want = self.image_size(view)
            first = next(files[view] for files in self.files if files[view] is not None)
            raise CaptureError(f"{path}: {what} {w}x{h} px but view {self.grid.name(view)} is {want[0]}x{want[1]} px "
                               f"in {first}; a view keeps one size (one of the two images is not this view's)")
        return img

    def __iter__(self) -> Iterator[np.ndarray]:
        for f in range(len(self)):
            yield self.load_frame(f)


def _open_videos(root: Path, grid: ViewGrid) -> CaptureSet:
    videos = video_files(root)
    if not videos:
        raise CaptureError(f"{root}: no videos found (looked for {', '.join(VIDEO_EXTENSIONS)} files)")
    if len(videos) != grid.num_views:
        raise CaptureError(f"{root}: {len(videos)} videos ({', '.join(p.name for p in videos)}) but the {grid} grid "
                           f"has {grid.num_views} views (one video per view, in name order, row-major)")
    infos = [video_info(p) for p in videos]
    counts = [n for n, _ in infos]
    n = min(counts)
    notes = []
    if len(set(counts)) > 1:
        lengths = ", ".join(f"{p.name} {c}" for p, c in zip(videos, counts, strict=True))
        notes.append(f"the videos differ in length ({lengths} frames); frames are matched by index, so only the "
                     f"first {n} are used")
    names = tuple(f"{f:05d}" for f in range(n))
    return CaptureSet(root, "video", grid, names, tuple(tuple(videos) for _ in range(n)), infos[0][1], tuple(notes),
                      tuple(size for _, size in infos))


def as_grid(grid: ViewGrid | tuple[int, int] | str) -> ViewGrid:
    """A `ViewGrid` from itself, a (rows, cols) pair or the CLI's spelling ``"2x2"``.

    Raises:
        ValueError: anything else, naming what was given."""
    if isinstance(grid, ViewGrid):
        return grid
    if isinstance(grid, str):  # the CLI's spelling, "2x2"
        parts = grid.lower().split("x")
        if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
            raise ValueError(f"grid {grid!r}: expected ROWSxCOLS such as '2x2', a (rows, cols) pair or a ViewGrid")
        grid = (int(parts[0]), int(parts[1]))
    if not isinstance(grid, tuple | list) or len(grid) != 2 or not all(
            isinstance(n, int | np.integer) and not isinstance(n, bool) for n in grid):
        raise ValueError(f"grid {grid!r}: expected a (rows, cols) pair of whole numbers, 'RxC' or a ViewGrid")
    return ViewGrid(int(grid[0]), int(grid[1]))


def open_capture(path: str | os.PathLike, grid: ViewGrid | tuple[int, int], layout: str = "auto",
                 missing: str = "error") -> CaptureSet:
    """Open a capture folder in one of the `LAYOUTS`; see the module docstring.

    Args:
        missing: a frame without one of its view images is an ``"error"`` (default), or ``"unseen"``: that
            view-frame counts as "board not seen" (`MISSING_VIEW`).

    Raises:
        CaptureError: missing folder, no frames, missing or extra views, a grid that does not match the files,
            unreadable first images, images of different sizes, a mosaic that does not divide into the grid,
            unreadable videos or a number of videos other than the grid's views.
    """
    root = Path(path)
    grid = as_grid(grid)
    if layout not in LAYOUTS:
        raise CaptureError(f"{root}: unknown layout {layout!r}; choose from {', '.join(LAYOUTS)}")
    if missing not in MISSING_VIEW:
        raise CaptureError(f"{root}: unknown missing-view mode {missing!r}; choose from {', '.join(MISSING_VIEW)}")
    if not root.exists():
        raise CaptureError(f"{root}: input folder does not exist")
    if not root.is_dir():
        raise CaptureError(f"{root}: input must be a folder of images, not a file")
    guessed = ""
    if layout == "auto":
        layout = detect_layout(root, grid)
        if layout == "mosaic":
            # no file name says anything about views: say so, so that a later error can be read in that light
            guessed = (f"layout guessed as 'mosaic' (no file is named like another layout: rRR_cCC or input_CamNNN "
                       f"views in frame folders, left*/right* pairs, or one video per view), so each image is one "
                       f"frame holding the {grid} views tiled row-major; pass --layout if that is wrong")
    if layout == "video":
        return _open_videos(root, grid)
    names, files = frame_files(root, grid, layout, missing)
    if not files:
        raise CaptureError(f"{root}: no frames found for the {layout} layout")
    first = files[0]
    if layout == "mosaic":
        img = _read(first[0], True)
        h_all, w_all = img.shape[:2]
        if h_all % grid.rows or w_all % grid.cols:
            raise CaptureError(f"{first[0]}: a {w_all}x{h_all} mosaic does not divide into a {grid} grid"
                               + (f"; {guessed}" if guessed else ""))
        size, sizes = (w_all // grid.cols, h_all // grid.rows), None
    else:  # each view's size from its first image (a view missing from the first frame: its first frame)
        firsts = [next((views[v] for views in files if views[v] is not None), None) for v in range(grid.num_views)]
        sizes = [_read(p, True).shape[1::-1] if p is not None else None for p in firsts]
        size = next(s for s in sizes if s is not None)
        sizes = tuple(tuple(int(x) for x in (s or size)) for s in sizes)
    notes = [guessed] if guessed else []
    absent = [(names[f], grid.name(v)) for f, views in enumerate(files) for v, p in enumerate(views) if p is None]
    if absent:
        listed = ", ".join(f"{name}/{view}" for name, view in absent[:5]) + (", ..." if len(absent) > 5 else "")
        notes.append(f"{len(absent)} view image(s) missing, counted as 'board not seen': {listed}")
    return CaptureSet(root, layout, grid, tuple(names), tuple(files), tuple(int(x) for x in size), tuple(notes),
                      sizes)


def write_frame(out_dir: str | os.PathLike, frame_name: str, images: np.ndarray, grid: ViewGrid,
                layout: str = "folders", ext: str = ".png") -> list[Path]:
    """Write one frame's (V, H, W[, 3]) views in a layout, each file atomically. Returns the written paths."""
    out = Path(out_dir)
    images = np.asarray(images)
    if images.shape[0] != grid.num_views:
        raise ValueError(f"a {grid} frame needs {grid.num_views} views, got {images.shape[0]}")
    if layout == "mosaic":
        targets = [(out / f"{frame_name}{ext}", tile_mosaic(images, grid))]
    elif layout == "folders":
        targets = [(out / frame_name / f"{grid.name(v)}{ext}", images[v]) for v in range(grid.num_views)]
    elif layout == "hci":
        targets = [(out / frame_name / f"input_Cam{v:03d}{ext}", images[v]) for v in range(grid.num_views)]
    else:
        raise ValueError(f"write_frame supports folders, mosaic and hci, got {layout!r}")
    for path, img in targets:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            if not cv2.imwrite(str(tmp), img):
                raise OSError(f"could not write {path}")
    return [p for p, _ in targets]


def check_frame_array(images: object, frame: int, grid, image_size_px: tuple[int, int] | Sequence[tuple[int, int]],
                      what: str = "frame") -> None:
    """Refuse a frame the tracking cannot use, naming it and what it should be: (V, H, W) 8-bit grayscale, one
    image per view of ``grid``, each ``image_size_px`` (width, height). With per-view sizes that differ (a mixed
    rig), a sequence of V (H, W) arrays, each its view's size.

    Raises:
        TypeError: not a numpy array (a list of them for a mixed rig).
        ValueError: the wrong number of dimensions (colour), dtype, view count or size, or NaN.
    """
    sizes = [tuple(int(x) for x in s) for s in np.asarray(image_size_px, dtype=np.int64).reshape(-1, 2)]
    if len(set(sizes)) > 1:
        _check_mixed_frame(images, frame, grid, sizes, what)
        return
    w, h = sizes[0]
    want = f"(V={grid.num_views}, H={h}, W={w}) uint8 grayscale"
    if not isinstance(images, np.ndarray):
        raise TypeError(f"{what} {frame}: expected a numpy array {want}, got {type(images).__name__}")
    if images.ndim == 4:
        raise ValueError(f"{what} {frame}: shape {images.shape} looks like colour images; convert each view to "
                         f"grayscale (cv2.cvtColor(..., cv2.COLOR_BGR2GRAY)) to get {want}")
    if images.ndim != 3:
        raise ValueError(f"{what} {frame}: shape {images.shape}; expected {want} (one image per view, stacked)")
    _check_dtype(images, frame, what, want)
    if images.shape[0] != grid.num_views or images.shape[1:3] != (h, w):
        raise ValueError(f"{what} {frame} has {images.shape[0]} views of {images.shape[2]}x{images.shape[1]} px but "
                         f"the calibration is a {grid} grid of {w}x{h} px views")


def _check_dtype(images: np.ndarray, frame: int, what: str, want: str) -> None:
    if images.dtype != np.uint8:
        hint = " (16-bit: scale with (img >> 8).astype(np.uint8))" if images.dtype == np.uint16 else \
            " (floats: clip to 0-255 and convert with .astype(np.uint8))" if images.dtype.kind == "f" else ""
        raise ValueError(f"{what} {frame}: dtype {images.dtype}; expected {want}{hint}")


def _check_mixed_frame(images: object, frame: int, grid, sizes: list[tuple[int, int]], what: str) -> None:
    want = f"{grid.num_views} uint8 grayscale (H, W) arrays, one per view in its own size"
    if isinstance(images, np.ndarray) or not isinstance(images, Sequence) or \
            not all(isinstance(i, np.ndarray) for i in images):
        raise TypeError(f"{what} {frame}: the calibration's views differ in size: expected a list of {want}, got "
                        f"{type(images).__name__}")
    if len(images) != grid.num_views:
        raise ValueError(f"{what} {frame} has {len(images)} views but the calibration is a {grid} grid")
    for v, (img, (w, h)) in enumerate(zip(images, sizes, strict=True)):
        if img.ndim != 2:
            raise ValueError(f"{what} {frame}, view {grid.name(v)}: shape {img.shape}; expected one grayscale "
                             f"{w}x{h} image (convert colour with cv2.cvtColor(..., cv2.COLOR_BGR2GRAY))")
        _check_dtype(img, frame, what, want)
        if img.shape != (h, w):
            raise ValueError(f"{what} {frame}, view {grid.name(v)} is {img.shape[1]}x{img.shape[0]} px but the "
                             f"calibration is for {w}x{h} px")


def check_frames_argument(frames: object, where: str) -> None:
    """Refuse, with a message naming the argument, what is not an iterable of frames: None, a single (V, H, W) array
    (one frame must be passed as ``[images]``), a string.

    Raises:
        TypeError: naming ``where`` and what it got.
    """
    if frames is None or isinstance(frames, str | bytes):
        raise TypeError(f"{where}: frames must be an iterable of (V, H, W) uint8 arrays (e.g. capture.frames()), "
                        f"got {type(frames).__name__}")
    if isinstance(frames, np.ndarray) and frames.ndim == 3:
        raise TypeError(f"{where}: frames is one (V, H, W) array; pass an iterable of frames, e.g. [images]")
