"""Which files of a capture folder are which view of which frame, per layout (`lfgraph.io.capture` documents the
layouts): the layout guess, the frame folders of rRR_cCC or input_CamNNN images, view folders, mosaics, left/right
pairs and Middlebury scene folders, in natural order."""

from __future__ import annotations

import re
from pathlib import Path

from lfgraph.core.errors import CaptureError
from lfgraph.core.grid import ViewGrid

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm", ".mpg", ".mpeg", ".wmv")
_VIEW_RE = re.compile(r"^r(\d+)_c(\d+)$")
_HCI_RE = re.compile(r"^input_Cam(\d+)$")
_PAIR_RE = re.compile(r"^(left|right)(.*)$")
MIDDLEBURY_VIEWS = ("im0", "im1")  # Middlebury 2014's left and right view images of a scene folder
MIDDLEBURY_CALIB = "calib.txt"  # beside them: what tells a scene folder from a capture's images on auto-detection
# the scene folder's other images (other exposures and lightings, occlusion masks, disparities), not frames of a mosaic
_MIDDLEBURY_OTHER_RE = re.compile(r"^(im\d+[EL]|mask\d+nocc|disp\d.*)$")


def _natural_key(name: str) -> list:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def _images(folder: Path) -> list[Path]:
    return sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS),
                  key=lambda p: _natural_key(p.name))


def video_files(folder: Path) -> list[Path]:
    """Video files directly in ``folder`` (`VIDEO_EXTENSIONS`, any case), in natural order (``v2`` before ``v10``)."""
    return sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in VIDEO_EXTENSIONS),
                  key=lambda p: _natural_key(p.name))


MAX_LISTED = 5  # an error lists at most this many missing views


def _view_files(folder: Path, grid: ViewGrid, missing: str = "error") -> tuple[Path | None, ...] | None:
    """Row-major view files of one frame folder (rRR_cCC or input_CamNNN names), None when it has neither; a view
    without a file is an error, or None in the tuple with ``missing="unseen"``."""
    found: dict[int, Path] = {}
    positions = []
    for p in _images(folder):
        m = _VIEW_RE.match(p.stem)
        h = _HCI_RE.match(p.stem)
        if m:
            r, c = int(m.group(1)), int(m.group(2))
            positions.append((r, c))
            if r < grid.rows and c < grid.cols:
                found[grid.index(r, c)] = p
        elif h:
            idx = int(h.group(1))
            positions.append(divmod(idx, grid.cols) if idx < grid.num_views else (idx, 0))
            if idx < grid.num_views:
                found[idx] = p
    if not positions:
        return None
    rows = max(r for r, _ in positions) + 1
    cols = max(c for _, c in positions) + 1
    if rows > grid.rows or cols > grid.cols:
        raise CaptureError(f"{folder}: the grid does not match the files: they reach row {rows - 1}, column "
                           f"{cols - 1}, but the grid is {grid} (rows 0..{grid.rows - 1}, columns 0..{grid.cols - 1})")
    absent = [grid.name(v) for v in range(grid.num_views) if v not in found]
    if absent and missing == "error":
        if len(absent) > len(found):  # most of the grid is not there: the grid, not a file, is wrong
            raise CaptureError(f"{folder}: holds {len(found)} view image(s) but the {grid} grid has {grid.num_views} "
                               f"views ({len(absent)} missing, e.g. {', '.join(absent[:MAX_LISTED])}); check --grid")
        listed = ", ".join(absent[:MAX_LISTED]) + (f" and {len(absent) - MAX_LISTED} more"
                                                    if len(absent) > MAX_LISTED else "")
        raise CaptureError(f"{folder}: missing view(s) {listed} of the {grid} grid (--missing-view unseen "
                           f"counts a missing view image as 'board not seen')")
    return tuple(found.get(v) for v in range(grid.num_views))


_TRAILING_NUMBER_RE = re.compile(r"^(.*?)(\d+)$")


def _view_folder_frames(root: Path, grid: ViewGrid, missing: str) -> tuple[list[str], list[tuple[Path | None, ...]]]:
    """The ``views`` layout: one folder per view, frames keyed by the number ending each file name."""
    folders = sorted((p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")),
                     key=lambda p: _natural_key(p.name))
    if len(folders) != grid.num_views:
        raise CaptureError(f"{root}: the views layout needs one folder per view, {grid.num_views} for the {grid} grid; "
                           f"found {len(folders)} ({', '.join(p.name for p in folders[:MAX_LISTED])})")
    per_view: list[dict[str, Path]] = []
    for folder in folders:
        keyed: dict[str, Path] = {}
        for p in _images(folder):
            m = _TRAILING_NUMBER_RE.match(p.stem)
            if m is None:
                raise CaptureError(f"{p}: the views layout matches frames by the number ending each file name; "
                                   f"this name has none")
            key = str(int(m.group(2)))
            if key in keyed:
                raise CaptureError(f"{p}: frame number {key} appears twice in {folder} (also {keyed[key].name})")
            keyed[key] = p
        if not keyed:
            raise CaptureError(f"{folder}: no images in this view's folder")
        per_view.append(keyed)
    keys = sorted(set().union(*per_view), key=int)
    files = [tuple(view.get(k) for view in per_view) for k in keys]
    if missing == "error":
        for k, views in zip(keys, files, strict=True):
            lacking = [folders[v].name for v, p in enumerate(views) if p is None]
            if lacking:
                raise CaptureError(f"{root}: frame {k} has no image in {', '.join(lacking)} (--missing-view unseen "
                                   f"counts a missing view image as 'board not seen')")
    return keys, files


def _scene_views(folder: Path) -> tuple[Path | None, Path | None] | None:
    """(im0, im1) of a Middlebury scene folder (None for one it lacks), None when it holds neither."""
    found: dict[str, Path] = {}
    for p in _images(folder):
        if p.stem in MIDDLEBURY_VIEWS:
            if p.stem in found:
                raise CaptureError(f"{p}: two images of view {p.stem} in this scene folder (also {found[p.stem].name})")
            found[p.stem] = p
    return None if not found else (found.get("im0"), found.get("im1"))


def _is_scene(folder: Path) -> bool:
    """A Middlebury 2014 scene folder: ``im0`` and ``im1`` images with ``calib.txt`` beside them."""
    views = _scene_views(folder)
    return views is not None and None not in views and (folder / MIDDLEBURY_CALIB).is_file()


def _middlebury_files(root: Path, grid: ViewGrid, missing: str) -> tuple[list[str], list[tuple[Path | None, ...]]]:
    """The middlebury layout: ``im0``/``im1`` of one scene folder (one frame), or of each scene folder in ``root``
    (one frame per folder, in natural name order)."""
    if (grid.rows, grid.cols) != (1, 2):
        raise CaptureError(f"{root}: the middlebury layout (im0/im1 scene folders) is a 1x2 grid, not {grid}")
    single = _scene_views(root)
    folders = [root] if single is not None else sorted(
        (d for d in root.iterdir() if d.is_dir() and not d.name.startswith(".") and _scene_views(d) is not None),
        key=lambda d: _natural_key(d.name))
    calibs = [d / MIDDLEBURY_CALIB for d in folders if (d / MIDDLEBURY_CALIB).is_file()]
    for other in calibs[1:]:  # frames of one capture are one rig's: Middlebury calibrates each scene on its own
        if other.read_bytes() != calibs[0].read_bytes():
            raise CaptureError(f"{other}: differs from {calibs[0]}: scenes of different calibrations are different "
                               f"captures; open one scene folder")
    names, files = [], []
    for d in folders:
        views = _scene_views(d)
        absent = [MIDDLEBURY_VIEWS[v] for v, p in enumerate(views) if p is None]
        if absent and missing == "error":
            raise CaptureError(f"{d}: no {absent[0]} image in this Middlebury scene folder (--missing-view unseen "
                               f"counts a missing view image as 'board not seen')")
        names.append(d.name)
        files.append(views)
    return names, files


def detect_layout(root: Path, grid: ViewGrid) -> str:
    """Guess the layout of the capture folder ``root`` from the files in it.

    Args:
        root: the capture folder.
        grid: the camera array (the ``views`` layout needs one folder per view).

    Returns:
        ``hci`` or ``folders`` (input_CamNNN or rRR_cCC images, at the top or in frame folders), ``pairs`` (every image
        named left*/right*), ``middlebury`` (im0/im1 images with calib.txt beside them, at the top or in scene
        folders), ``mosaic`` (other images), ``video``, or ``views`` (no top-level images or videos, one image folder
        per view of a grid of two or more views).

    Raises:
        CaptureError: no images, frame folders or videos found, or the folder holds inputs of more than one layout.
    """
    images = _images(root)
    subdirs = [p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")]
    view_named = [p for p in images if _VIEW_RE.match(p.stem) or _HCI_RE.match(p.stem)]
    pair_named = [p for p in images if _PAIR_RE.match(p.stem)]
    videos = video_files(root)
    frame_dirs = [d for d in subdirs if any(_VIEW_RE.match(p.stem) or _HCI_RE.match(p.stem) for p in _images(d))]
    scene_dirs = [d for d in subdirs if _is_scene(d)]
    candidates = []
    if _is_scene(root) or scene_dirs:
        candidates.append("middlebury")
        if _is_scene(root):  # the scene's own files are not frames of another layout
            images = [p for p in images if p.stem not in MIDDLEBURY_VIEWS and not _MIDDLEBURY_OTHER_RE.match(p.stem)]
        subdirs = [d for d in subdirs if d not in scene_dirs]
    if view_named or frame_dirs:
        sample = view_named or _images(frame_dirs[0])
        candidates.append("hci" if any(_HCI_RE.match(p.stem) for p in sample) else "folders")
    if pair_named and len(pair_named) == len(images):
        candidates.append("pairs")
    other = [p for p in images if p not in view_named and p not in pair_named]
    if other:
        candidates.append("mosaic")
    if videos:
        candidates.append("video")
    if not images and not frame_dirs and not videos and not scene_dirs and len(subdirs) == grid.num_views > 1 \
            and all(_images(d) for d in subdirs):
        candidates.append("views")
    if not candidates:
        raise CaptureError(f"{root}: no images found (looked for {', '.join(IMAGE_EXTENSIONS)} files, frame "
                           f"folders holding rRR_cCC or input_CamNNN images, and {', '.join(VIDEO_EXTENSIONS)} "
                           f"videos)")
    if len(candidates) > 1:
        raise CaptureError(f"{root}: ambiguous layout, it holds {', '.join(candidates)} inputs "
                           f"({len(frame_dirs)} frame folders, {len(view_named)} view images, {len(other)} other "
                           f"images, {len(videos)} videos, {len(scene_dirs)} Middlebury scene folders); pass --layout "
                           f"or clean the folder")
    return candidates[0]


def frame_files(root: Path, grid: ViewGrid, layout: str,
                 missing: str) -> tuple[list[str], list[tuple[Path | None, ...]]]:
    """(frame names, per frame the image of each view — None where missing) of an image layout."""
    names: list[str] = []
    files: list[tuple[Path | None, ...]] = []
    if layout in ("folders", "hci"):
        single = _view_files(root, grid, missing)
        if single is not None:
            return [root.name], [single]
        for d in sorted((p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")),
                        key=lambda p: _natural_key(p.name)):
            views = _view_files(d, grid, missing)
            if views is not None:
                names.append(d.name)
                files.append(views)
        return names, files
    if layout == "views":
        return _view_folder_frames(root, grid, missing)
    if layout == "middlebury":
        return _middlebury_files(root, grid, missing)
    if layout == "mosaic":
        images = _images(root)
        return [p.stem for p in images], [(p,) for p in images]
    return _pair_files(root, grid, missing)


def _pair_files(root: Path, grid: ViewGrid, missing: str) -> tuple[list[str], list[tuple[Path | None, ...]]]:
    """The pairs layout: ``left*``/``right*`` images matched by what follows the side's name."""
    if (grid.rows, grid.cols) != (1, 2):
        raise CaptureError(f"{root}: the pairs layout (left*/right* images) is a 1x2 grid, not {grid}")
    sides: dict[str, dict[str, Path]] = {"left": {}, "right": {}}
    for p in _images(root):
        m = _PAIR_RE.match(p.stem)
        if m:
            sides[m.group(1)][m.group(2)] = p
    for side, other in (("left", "right"), ("right", "left")):
        lonely = sorted(set(sides[side]) - set(sides[other]), key=_natural_key)
        if lonely and missing == "error":
            raise CaptureError(f"{sides[side][lonely[0]]}: no {other} image for this {side} image (--missing-view "
                               f"unseen counts a missing view image as 'board not seen')")
    keys = sorted(set(sides["left"]) | set(sides["right"]), key=_natural_key)
    return keys, [(sides["left"].get(k), sides["right"].get(k)) for k in keys]


