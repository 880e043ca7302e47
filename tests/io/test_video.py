"""The ``video`` input layout (one video per view, frames matched by index) and missing view images
(``missing="unseen"``), on rendered boards packed into small MJPG videos written here with cv2.VideoWriter."""

import os
import pickle
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from lfgraph.cli import main
from lfgraph.core.calibration import Calibration
from lfgraph.datasets.checkerboard import CheckerboardTruth
from lfgraph.detect.board import BoardSpec
from lfgraph.detect.detections import detect_capture
from lfgraph.io.capture import CaptureError, open_capture
from lfgraph.io.video import close_videos

FRAMES = 10
BOARD = BoardSpec.parse("7x5", 15)
DETECTION_RMS_PX = 0.3  # corners found in MJPG frames against the true corners (PNG frames do about 0.1 px)
RIG_RMS_PX = 0.5
MAX_POSITION_ERROR_MM = 2.0
RECORDED_GREY_LEVELS = 3.0  # mean |recorded JPEG - decoded video frame| of a frame's own image (another frame's: tens)


@pytest.fixture(scope="module")
def rendered(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("render") / "small"
    assert main(["synth", "checkerboard", str(out), "--scene", "small-2x2", "--frames", str(FRAMES), "--jobs", "2",
                 "--quiet", "--seed", "3"]) == 0
    return out


def write_videos(src: Path, dst: Path, frames: list[int] | None = None, lengths: dict[int, int] | None = None) -> Path:
    """One MJPG .avi per view (cam_0 .. cam_3, row-major) of the rendered frames (view v: ``lengths[v]`` frames)."""
    dst.mkdir(parents=True, exist_ok=True)
    names = sorted(p.name for p in src.iterdir() if p.is_dir())
    frames = list(range(len(names))) if frames is None else frames
    for v, view in enumerate(("r00_c00", "r00_c01", "r01_c00", "r01_c01")):
        first = cv2.imread(str(src / names[0] / f"{view}.png"))
        h, w = first.shape[:2]
        writer = cv2.VideoWriter(str(dst / f"cam_{v}.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (w, h))
        assert writer.isOpened()
        for f in frames[: (lengths or {}).get(v, len(frames))]:
            writer.write(cv2.imread(str(src / names[f] / f"{view}.png")))
        writer.release()
    return dst


def decode_all(path: Path) -> list[np.ndarray]:
    """Every frame of a video, read sequentially with OpenCV (the reference for the layout's random access)."""
    reader = cv2.VideoCapture(str(path))
    out = []
    while True:
        ok, img = reader.read()
        if not ok:
            break
        out.append(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))
    reader.release()
    return out


@pytest.fixture(scope="module")
def videos(rendered, tmp_path_factory) -> Path:
    return write_videos(rendered, tmp_path_factory.mktemp("video") / "cams")


def test_video_layout_frames_match_sequential_decoding(videos, rendered):
    capture = open_capture(videos, (2, 2))
    assert capture.layout == "video" and len(capture) == FRAMES and capture.notes == ()
    png = cv2.imread(str(rendered / "000" / "r00_c00.png"), cv2.IMREAD_GRAYSCALE)
    assert capture.image_size_px == (png.shape[1], png.shape[0])
    reference = [decode_all(videos / f"cam_{v}.avi") for v in range(4)]
    assert all(len(r) == FRAMES for r in reference)
    for f in [0, 1, 2, 7, 3, 9, 8, 0, 5]:  # in order, skipping ahead, and backwards (seeks)
        frame = capture.load_frame(f)
        for v in range(4):
            np.testing.assert_array_equal(frame[v], reference[v][f], err_msg=f"frame {f} view {v}")
    again = pickle.loads(pickle.dumps(capture))  # detection ships captures to worker processes
    close_videos()
    np.testing.assert_array_equal(again.load_frame(4)[2], reference[2][4])
    assert again.load_frame(6, grayscale=False).shape == (4, png.shape[0], png.shape[1], 3)
    with pytest.raises(IndexError):
        capture.load_view(FRAMES, 0)


def test_video_detection_against_truth_and_cache(videos, rendered, tmp_path):
    src = tmp_path / "cams"
    shutil.copytree(videos, src)
    capture = open_capture(src, (2, 2), "video")
    obs, cached = detect_capture(capture, BOARD, jobs=2, progress=False)
    assert not cached and obs.sources[3][1].endswith("cam_1.avi")
    truth = CheckerboardTruth.load_npz(rendered / "truth_corners.npz")
    both = obs.seen & truth.board_visible
    assert both.sum() >= 0.8 * truth.board_visible.sum()
    err = (obs.corners_px - truth.corners_px)[both]
    assert np.sqrt(np.mean(np.sum(err**2, axis=-1))) < DETECTION_RMS_PX
    assert detect_capture(open_capture(src, (2, 2)), BOARD, jobs=1, progress=False)[1]  # cached now
    stat = (src / "cam_2.avi").stat()
    os.utime(src / "cam_2.avi", ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))  # a re-encoded video
    again, cached = detect_capture(open_capture(src, (2, 2)), BOARD, jobs=1, progress=False)
    assert not cached
    np.testing.assert_array_equal(again.valid, obs.valid)


def test_calibrate_cli_on_videos(videos, rendered, tmp_path, capsys):
    out = tmp_path / "calibration.json"
    code = main(["calibrate", str(videos), "--grid", "2x2", "--board", "7x5", "--square-mm", "15", "--jobs", "2",
                 "--quiet", "--no-cache", "-o", str(out)])
    text = capsys.readouterr()
    assert code == 0, text.err
    assert f"video layout, {FRAMES} frames x 4 views" in text.out
    calib, truth = Calibration.load(out), Calibration.load(rendered / "truth.json")
    assert calib.metrics["rig_rms_px"] < RIG_RMS_PX
    err_mm = 1e3 * np.abs(np.stack(calib.ref_T_view)[:, :3, 3] - np.stack(truth.ref_T_view)[:, :3, 3])
    assert err_mm.max() < MAX_POSITION_ERROR_MM


def test_a_recording_reads_a_videos_frames_ahead_and_in_order(videos, tmp_path):
    """A calibration's recording reads its frames on a worker thread ahead of the frame being logged (a video
    reader is used by that one thread, in order): every frame's recorded images are that frame's."""
    from lfgraph.core.grid import ViewGrid
    from lfgraph.viz import RerunLogger

    capture = open_capture(videos, (2, 2))
    decoded = [decode_all(videos / f"cam_{v}.avi") for v in range(4)]
    seen = []
    with RerunLogger.to_file(tmp_path / "v.rrd", ViewGrid(2, 2, 0)) as logger:
        for f, encoded in logger._encoded_frames(capture.load_frame, len(capture)):
            for v, image in enumerate(encoded):
                blob = np.asarray(image.blob.as_arrow_array().to_pylist()[0], dtype=np.uint8)
                recorded = cv2.imdecode(blob, cv2.IMREAD_GRAYSCALE).astype(float)
                assert np.mean(np.abs(recorded - decoded[v][f])) < RECORDED_GREY_LEVELS, (f, v)
            seen.append(f)
    assert seen == list(range(FRAMES))


def test_videos_of_different_lengths_use_the_shortest(rendered, tmp_path):
    folder = write_videos(rendered, tmp_path / "uneven", frames=[0, 1, 2, 3, 4], lengths={1: 3})
    capture = open_capture(folder, (2, 2))
    assert len(capture) == 3
    assert len(capture.notes) == 1 and "cam_1.avi 3" in capture.notes[0] and "first 3" in capture.notes[0]


def test_bad_video_inputs(rendered, videos, tmp_path):
    with pytest.raises(CaptureError, match=r"4 videos \(cam_0\.avi, .*\) but the 1x2 grid has 2 views"):
        open_capture(videos, (1, 2))
    odd = tmp_path / "odd"
    shutil.copytree(videos, odd)
    writer = cv2.VideoWriter(str(odd / "cam_3.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    writer.write(np.zeros((48, 64, 3), np.uint8))
    writer.release()
    assert open_capture(odd, (2, 2)).image_sizes[3] == (64, 48)  # a rig of mixed sizes: each video keeps its own
    (odd / "cam_3.avi").write_bytes(b"not a video")
    with pytest.raises(CaptureError, match=r"cam_3\.avi: cannot"):
        open_capture(odd, (2, 2))
    mixed = tmp_path / "mixed"
    shutil.copytree(videos, mixed)
    shutil.copy(rendered / "000" / "r00_c00.png", mixed / "r00_c00.png")
    with pytest.raises(CaptureError, match="ambiguous layout.*video"):
        open_capture(mixed, (2, 2))


def test_missing_view_image_is_an_error_or_unseen(rendered, tmp_path, capsys):
    src = tmp_path / "frames"
    shutil.copytree(rendered, src)
    full, _ = detect_capture(open_capture(src, (2, 2)), BOARD, jobs=1, progress=False, cache=False)
    f = next(f for f in range(FRAMES) if full.seen[1, f])  # a frame in which view r00_c01 saw the board
    name = full.frame_names[f]
    (src / name / "r00_c01.png").unlink()
    with pytest.raises(CaptureError, match=rf"{name}: missing view\(s\) r00_c01 of the 2x2 grid"):
        open_capture(src, (2, 2))
    capture = open_capture(src, (2, 2), missing="unseen")
    assert capture.files[f][1] is None and capture.is_missing(f, 1) and "r00_c01" in capture.notes[0]
    assert not capture.load_frame(f)[1].any()  # a missing view loads black
    obs, _ = detect_capture(capture, BOARD, jobs=2, progress=False)
    expected = full.seen.copy()
    expected[1, f] = False
    np.testing.assert_array_equal(obs.seen, expected)
    np.testing.assert_array_equal(obs.corners_px[obs.valid], full.corners_px[obs.valid])
    assert "(missing)" in obs.describe(1, f)
    out = tmp_path / "calibration.json"
    args = ["calibrate", str(src), "--grid", "2x2", "--board", "7x5", "--square-mm", "15", "--jobs", "2", "--quiet",
            "-o", str(out)]
    assert main(args) == 1 and not out.exists()
    assert "missing view(s) r00_c01" in capsys.readouterr().err
    assert main([*args, "--missing-view", "unseen"]) == 0
    assert "1 view image(s) missing" in capsys.readouterr().out


def test_missing_pair_image_is_unseen(tmp_path):
    img = np.full((48, 64), 255, np.uint8)
    for name in ("left01", "right01", "left02", "right03"):
        cv2.imwrite(str(tmp_path / f"{name}.png"), img)
    with pytest.raises(CaptureError, match=r"left02\.png: no right image"):
        open_capture(tmp_path, (1, 2), "pairs")
    capture = open_capture(tmp_path, (1, 2), "pairs", missing="unseen")
    assert capture.frame_names == ("01", "02", "03")
    assert capture.is_missing(1, 1) and capture.is_missing(2, 0) and not capture.is_missing(0, 0)
