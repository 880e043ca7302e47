"""Input layouts: round trips, auto-detection, real data, and every error."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from lfgraph.core.grid import ViewGrid
from lfgraph.io.capture import CaptureError, open_capture, split_mosaic, tile_mosaic, write_frame

GRID = ViewGrid(2, 2)


def _frames(n: int = 3, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (4, 24, 32), dtype=np.uint8) for _ in range(n)]


@pytest.mark.parametrize("layout", ["folders", "mosaic", "hci"])
def test_round_trip_and_auto_detection(tmp_path, layout):
    frames = _frames()
    names = ["frame2", "frame10", "frame1"]  # natural order: 1, 2, 10
    for name, imgs in zip(names, frames, strict=True):
        write_frame(tmp_path, name, imgs, GRID, layout=layout)
    cap = open_capture(tmp_path, GRID)
    assert cap.layout == layout
    assert cap.frame_names == ("frame1", "frame2", "frame10")
    assert cap.image_size_px == (32, 24)
    assert np.array_equal(cap.load_frame(2), frames[1])
    assert np.array_equal(cap.load_view(0, 3), frames[2][3])
    assert len(list(cap)) == 3


def test_single_folder_is_one_frame(tmp_path):
    imgs = _frames(1)[0]
    for v in range(4):
        cv2.imwrite(str(tmp_path / f"{GRID.name(v)}.png"), imgs[v])
    cap = open_capture(tmp_path, (2, 2))
    assert len(cap) == 1 and np.array_equal(cap.load_frame(0), imgs)


def test_mosaic_helpers_invert_each_other():
    imgs = _frames(1)[0]
    assert np.array_equal(split_mosaic(tile_mosaic(imgs, GRID), GRID), imgs)


def test_real_opencv_stereo_pairs(test_data):
    cap = open_capture(test_data / "opencv_stereo", (1, 2))
    assert cap.layout == "pairs" and len(cap) == 13 and "10" not in cap.frame_names
    assert cap.image_size_px == (640, 480)
    assert cap.load_frame(0).shape == (2, 480, 640)


def _folders(tmp_path, n=2):
    for i, imgs in enumerate(_frames(n)):
        write_frame(tmp_path, f"{i:03d}", imgs, GRID)
    return tmp_path


def test_missing_view(tmp_path):
    (_folders(tmp_path) / "001" / "r01_c00.png").unlink()
    with pytest.raises(CaptureError, match=r"001: missing view\(s\) r01_c00"):
        open_capture(tmp_path, GRID)


def test_files_beyond_the_grid(tmp_path):
    _folders(tmp_path)
    cv2.imwrite(str(tmp_path / "000" / "r02_c00.png"), np.zeros((24, 32), np.uint8))
    with pytest.raises(CaptureError, match="000: the grid does not match the files: they reach row 2"):
        open_capture(tmp_path, GRID)


def test_unreadable_image(tmp_path):
    _folders(tmp_path)
    (tmp_path / "001" / "r00_c01.png").write_bytes(b"not a png")
    cap = open_capture(tmp_path, GRID)  # only the first frame is read when opening
    with pytest.raises(CaptureError, match=r"001/r00_c01.png: cannot read"):
        cap.load_frame(1)


def test_images_of_different_sizes(tmp_path):
    _folders(tmp_path)
    cv2.imwrite(str(tmp_path / "000" / "r01_c01.png"), np.zeros((20, 32), np.uint8))
    cv2.imwrite(str(tmp_path / "001" / "r01_c01.png"), np.zeros((20, 32), np.uint8))
    mixed = open_capture(tmp_path, GRID)  # a rig of mixed sizes: each view keeps its first image's size
    assert mixed.image_sizes[3] == (32, 20) and mixed.image_sizes[0] == (32, 24)
    assert [img.shape for img in mixed.load_frame(1)][2:] == [(24, 32), (20, 32)]
    with pytest.raises(CaptureError, match=r"r00_c00 32x24, .*r01_c01 32x20\); refine needs views of one size"):
        mixed.require_one_size("refine")
    cv2.imwrite(str(tmp_path / "000" / "r01_c01.png"), np.zeros((24, 32), np.uint8))
    with pytest.raises(CaptureError, match=r"001/r01_c01.png: image is 32x20 px but view r01_c01 is 32x24 px "
                                           r"in .*000/r01_c01.png"):
        open_capture(tmp_path, GRID).load_frame(1)


def test_mosaic_not_divisible(tmp_path):
    cv2.imwrite(str(tmp_path / "000.png"), np.zeros((49, 64), np.uint8))
    with pytest.raises(CaptureError, match=r"000.png: a 64x49 mosaic does not divide into a 2x2 grid"):
        open_capture(tmp_path, GRID)


def test_folder_problems(tmp_path):
    with pytest.raises(CaptureError, match="does not exist"):
        open_capture(tmp_path / "nope", GRID)
    (tmp_path / "file.png").write_bytes(b"")
    with pytest.raises(CaptureError, match="not a file"):
        open_capture(tmp_path / "file.png", GRID)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(CaptureError, match="empty: no images found"):
        open_capture(empty, GRID)
    with pytest.raises(CaptureError, match="unknown layout 'tiles'"):
        open_capture(empty, GRID, layout="tiles")
    with pytest.raises(CaptureError, match="no frames found"):
        open_capture(empty, GRID, layout="folders")


def test_ambiguous_layout(tmp_path):
    _folders(tmp_path)
    cv2.imwrite(str(tmp_path / "extra.png"), np.zeros((48, 64), np.uint8))
    with pytest.raises(CaptureError, match="ambiguous layout"):
        open_capture(tmp_path, GRID)
    assert open_capture(tmp_path, GRID, layout="folders").layout == "folders"


def test_pairs_errors(tmp_path):
    for name in ("left01.png", "right01.png", "left02.png"):
        cv2.imwrite(str(tmp_path / name), np.zeros((24, 32), np.uint8))
    with pytest.raises(CaptureError, match="left02.png: no right image"):
        open_capture(tmp_path, (1, 2))
    with pytest.raises(CaptureError, match="1x2 grid, not 2x2"):
        open_capture(tmp_path, GRID, layout="pairs")


def test_views_layout_matches_frames_by_number_in_real_trinocular_folders():
    """BoofCV's trinocular set: left/ middle/ right/ with leftN.jpg ...; frames matched by N, views in folder order."""
    from pathlib import Path

    from lfgraph.io.capture import open_capture

    root = Path(__file__).resolve().parents[1] / "data" / "trinocular"
    capture = open_capture(root, (1, 3))
    assert capture.layout == "views"
    assert capture.frame_names == ("1", "6", "11", "16", "21")
    assert [p.name for p in capture.paths(2)] == ["left11.jpg", "middle11.jpg", "right11.jpg"]
    assert capture.image_size_px == (1224, 1024)


def test_open_capture_validates_its_grid_and_frames_its_limit(tmp_path):
    """Issues 27/28: ``open_capture(dir, (2, 2, 2))`` was accepted, ``open_capture(dir, "2x2")`` a TypeError and
    ``frames(-1)`` silently empty."""
    from lfgraph.cli import main

    out = tmp_path / "s"
    assert main(["synth", "scene", str(out), "--scene", "small-2x2", "--frames", "1", "--quiet", "--jobs", "1"]) == 0
    assert open_capture(out, "2x2").grid.num_views == 4  # the CLI's spelling
    for bad in ((2, 2, 2), (2.0, 2), "2by2", None):
        with pytest.raises(ValueError, match="grid"):
            open_capture(out, bad)
    capture = open_capture(out, (2, 2))
    for bad in (-1, 0, 1.5):
        with pytest.raises(ValueError, match="limit"):
            list(capture.frames(bad))
    assert len(list(capture.frames(5))) == 1


# ---------------------------------------------------------------------------------------------- middlebury
SHARED_MIDDLEBURY = Path(__file__).resolve().parents[3] / "shared" / "data" / "middlebury2014_quarter"
MIDDLEBURY_CALIB = "cam0=[300 0 15.5; 0 300 11.5; 0 0 1]\ncam1=[300 0 17.5; 0 300 11.5; 0 0 1]\ndoffs=2\n" \
                   "baseline=100\nwidth=32\nheight=24\nndisp=16\n"


def _scene(folder: Path, seed: int = 0, calib: str = MIDDLEBURY_CALIB, views=("im0", "im1")) -> np.ndarray:
    """A Middlebury 2014 scene folder as the benchmark ships it: im0/im1, calib.txt and the scene's other files."""
    folder.mkdir(parents=True, exist_ok=True)
    imgs = _frames(1, seed)[0][:2]
    for name, img in zip(("im0", "im1"), imgs, strict=True):
        if name in views:
            cv2.imwrite(str(folder / f"{name}.png"), img)
    cv2.imwrite(str(folder / "mask0nocc.png"), np.full((24, 32), 255, np.uint8))
    cv2.imwrite(str(folder / "im1E.png"), imgs[1])  # another exposure of the right view
    (folder / "disp0GT.pfm").write_bytes(b"Pf\n32 24\n-1\n" + bytes(4 * 32 * 24))
    (folder / "calib.txt").write_text(calib)
    return imgs


def test_a_middlebury_scene_folder_is_a_pair(tmp_path):
    imgs = _scene(tmp_path / "Teddy")
    cap = open_capture(tmp_path / "Teddy", (1, 2))
    assert (cap.layout, cap.frame_names, cap.image_size_px) == ("middlebury", ("Teddy",), (32, 24))
    assert np.array_equal(cap.load_frame(0), imgs)  # im0 left (r00_c00), im1 right; im1E is not a view
    # scene folders of one rig (the same calib.txt): one frame each, in natural order
    second = _scene(tmp_path / "scene10", seed=1)
    _scene(tmp_path / "scene2", seed=2)
    (tmp_path / "Teddy").rename(tmp_path / "scene1")
    cap = open_capture(tmp_path, (1, 2))
    assert (cap.layout, cap.frame_names) == ("middlebury", ("scene1", "scene2", "scene10"))
    assert np.array_equal(cap.load_frame(2), second)


def test_middlebury_errors_name_the_folder(tmp_path):
    _scene(tmp_path / "a")
    with pytest.raises(CaptureError, match=r"a: the middlebury layout .* is a 1x2 grid, not 2x1"):
        open_capture(tmp_path / "a", (2, 1), "middlebury")
    _scene(tmp_path / "b", calib=MIDDLEBURY_CALIB.replace("baseline=100", "baseline=120"))
    with pytest.raises(CaptureError, match=r"b/calib\.txt: differs from .*a/calib\.txt: .*open one scene folder"):
        open_capture(tmp_path, (1, 2))
    _scene(tmp_path / "c", views=("im0",))
    with pytest.raises(CaptureError, match=r"c: no im1 image in this Middlebury scene folder"):
        open_capture(tmp_path / "c", (1, 2), "middlebury")
    cap = open_capture(tmp_path / "c", (1, 2), "middlebury", missing="unseen")
    assert cap.is_missing(0, 1) and not cap.is_missing(0, 0)


def test_numbered_images_without_calib_txt_stay_a_mosaic(tmp_path):
    """im0.png, im1.png, ... without calib.txt beside them are the frames of a mosaic capture, not a scene."""
    for f, imgs in enumerate(_frames(3)):
        cv2.imwrite(str(tmp_path / f"im{f}.png"), tile_mosaic(imgs, GRID))
    assert open_capture(tmp_path, GRID).layout == "mosaic"


@pytest.mark.skipif(not SHARED_MIDDLEBURY.is_dir(), reason="the shared Middlebury 2014 set is not beside the project")
def test_real_middlebury_scenes_open_at_their_calibrated_size():
    from lfgraph.interop import import_calibration

    scenes = sorted(p for p in SHARED_MIDDLEBURY.iterdir() if p.is_dir())
    assert len(scenes) == 6
    for scene in scenes:
        cap = open_capture(scene, (1, 2))
        assert cap.layout == "middlebury" and len(cap) == 1
        assert cap.image_size_px == import_calibration(scene, "middlebury").image_size_px
        assert cap.load_frame(0).shape == (2, cap.image_size_px[1], cap.image_size_px[0])
