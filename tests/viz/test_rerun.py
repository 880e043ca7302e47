"""rerun logging: the CLI's recordings, read back through rerun's own server (data) and rrd reader (blueprint).

What a newcomer must see is checked on the files: OpenCV coordinates on the world, both rigs, each frame's own
image and points on the ``frame`` timeline, outliers on their frame, a blueprint per command whose every view has
data, and a valid stream from ``--stdout``.
"""

import dataclasses
import subprocess
import sys

import numpy as np
import pytest
import rerun as rr
from rerun.chunk import RrdReader

from lfgraph.cli import main
from lfgraph.core.calibration import Calibration

SMALL = ["--grid", "2x2", "--board", "7x5", "--square-mm", "15", "--quiet"]
STDOUT_CLOSED_S = 120  # seconds: the command must end by itself once its reader has gone
CORNERS = 7 * 5
RDF = [3, 2, 5]  # rerun's ViewDir codes of Right, Down, Forward (OpenCV camera axes)
FRAMES = 10
RERUN_FOV_Y_DEG = 55.0  # the vertical field of view of rerun's 3-D eye (its default; a blueprint does not set it)
VIEW_ASPECT = 1.5  # width / height of the default layouts' 3-D view (measured on the screenshots, 1400x860 window)
RIG_MIN_WIDTH_SHARE = 1 / 3  # the rig spans at least this share of the 3-D view's width (issue 40: ~1/20)
RMS_CHART_REL = 0.1  # the RMS chart (graph error, priors included) against the stage's own RMS of the tracks
JPEG_CORNER_TOLERANCE_PX = 0.5  # median gap of OpenCV's corners (no sub-pixel step) on the JPEG to the logged ones

MAX_DECADES = 3  # the LM error chart's bars: decades fallen since the stage began, up to this many
CHANGE_LABEL_CHARS = 40  # a view's change label in the 3-D view stays about this short (readable on a 5x5)


def read_rrd(path, index):
    """(column names, static row, rows on ``index``) of a recording as {column: list}; pyarrow, no pandas (bar
    charts are arrow unions pandas cannot hold)."""
    with rr.server.Server(datasets={"run": [str(path)]}) as server:
        ds = server.client().get_dataset("run")
        columns = [c.name for c in ds.schema()]
        static = ds.reader(index=None).to_arrow_table().to_pydict()
        rows = None if index is None else \
            ds.reader(index=index, include_semantically_empty_columns=True).to_arrow_table().to_pydict()
    return columns, static, rows


def read_blueprint(path, eye: list | None = None):
    """The layout of a file recording — it holds exactly one: the logger sends it when it closes, knowing what was
    recorded and the rig (a second blueprint sent without being made active is one the viewer never shows) — as
    [(view class, origin, name)] and the time panel's timeline; ``eye`` (a list) gets the 3-D eye's (position,
    look target, up) when there is one."""
    reader = RrdReader(path)
    stores = reader.blueprints()
    assert len(stores) == 1, f"{path}: {len(stores)} blueprints"
    views, timeline = [], None
    for chunk in reader.stream(store=stores[0]):
        batch = chunk.to_record_batch()
        names = batch.schema.names
        if "ViewBlueprint:class_identifier" in names:
            get = {n: batch.column(n).to_pylist()[0][0] for n in names if n.startswith("ViewBlueprint:")}
            views.append((get["ViewBlueprint:class_identifier"], get["ViewBlueprint:space_origin"],
                          get.get("ViewBlueprint:display_name")))
        if "TimePanelBlueprint:timeline" in names:
            timeline = batch.column("TimePanelBlueprint:timeline").to_pylist()[0][0]
        if eye is not None and "EyeControls3D:position" in names:
            eye.append(tuple(np.array(batch.column(f"EyeControls3D:{c}").to_pylist()[0][0])
                             for c in ("position", "look_target", "eye_up")))
    return views, timeline


def view_share(eye, points):
    """(share of the 3-D view's width, of its height) that ``points`` span as rerun's eye ``eye`` (position, look
    target, up) draws them in a view of `VIEW_ASPECT` (1 = edge to edge), and how far the furthest of them lies from
    the centre (1 = on an edge, more: outside the view)."""
    position, target, up = eye
    forward = (target - position) / np.linalg.norm(target - position)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    rel = np.asarray(points) - position
    depth = rel @ forward
    assert np.all(depth > 0), "rig points behind the eye"
    tan_v = np.tan(np.radians(RERUN_FOV_Y_DEG) / 2)
    x = rel @ right / depth / (tan_v * VIEW_ASPECT)  # -1 .. 1 across the view
    y = rel @ up / depth / tan_v
    return (x.max() - x.min()) / 2, (y.max() - y.min()) / 2, max(np.abs(x).max(), np.abs(y).max())


def stream_rows(path, entity: str, column: str):
    """[(frame, value)] of one entity's column in the order it was logged (rerun's row ids), every row kept."""
    rows = []
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        meta = batch.schema.metadata or {}
        if meta.get(b"rerun:entity_path", b"").decode() != entity or column not in batch.schema.names:
            continue
        ids = batch.column("rerun.controls.RowId").to_pylist()
        frames = batch.column("frame").to_pylist() if "frame" in batch.schema.names else [None] * len(ids)
        rows += zip(ids, frames, batch.column(column).to_pylist(), strict=True)
    return [(f, v) for _, f, v in sorted(rows, key=lambda r: r[0])]


def last_per_frame(rows, column):
    """{frame: the last value logged at that frame} (later stages overwrite earlier ones)."""
    out = {}
    for f, value in zip(rows["frame"], rows[column], strict=True):
        if value is not None:
            out[int(f)] = value
    return out


def assert_every_view_has_data(views, columns):
    """'Nothing empty': each view of the blueprint has some logged entity under its origin."""
    for kind, origin, name in views:
        assert any(c.startswith(f"/{origin}") and ":" in c for c in columns), f"{kind} view {name!r} ({origin}) empty"


@pytest.fixture(scope="module")
def board_capture(tmp_path_factory):
    out = tmp_path_factory.mktemp("viz") / "small"
    assert main(["synth", "checkerboard", str(out), "--scene", "small-2x2", "--frames", str(FRAMES), "--jobs", "2",
                 "--quiet", "--seed", "5"]) == 0
    return out


@pytest.fixture(scope="module")
def calibrated(board_capture, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("cal")
    rrd, out = tmp / "calib.rrd", tmp / "c.json"
    assert main(["calibrate", str(board_capture), *SMALL, "-o", str(out), "--save", str(rrd)]) == 0
    assert rrd.exists() and not list(tmp.glob(".*.tmp"))
    return rrd, Calibration.load(out)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("scene") / "scene"
    assert main(["synth", "scene", str(out), "--scene", "small-2x2", "--frames", "2", "--shake-rot-deg", "0.5",
                 "--shake-trans-mm", "1", "--jobs", "2", "--quiet"]) == 0
    return out


@pytest.mark.slow
def test_calibrate_recording(calibrated):
    rrd, calib = calibrated
    columns, static, rows = read_rrd(rrd, "frame")
    assert static["/world:ViewCoordinates:xyz"][0] == [RDF]
    names = [calib.grid.name(v) for v in range(calib.num_views)]
    for v, name in enumerate(names):
        np.testing.assert_allclose(static[f"/world/calibrated_rig/{name}:Transform3D:translation"][0][0],
                                   calib.ref_T_view[v][:3, 3], atol=1e-9)
        assert static[f"/world/calibrated_rig/{name}:Pinhole:image_from_camera"][0]
    assert len({c.split(":")[0] for c in columns if c.startswith("/world/boards/frame_") and "Transform3D" in c}) \
        == FRAMES
    for name in names:
        images = last_per_frame(rows, f"/views/{name}/image:EncodedImage:blob")
        assert sorted(images) == list(range(FRAMES))  # every frame its own image...
        assert len({bytes(np.asarray(b[0], dtype=np.uint8)) for b in images.values()}) == FRAMES  # ...not frame 0's
        residuals = last_per_frame(rows, f"/views/{name}/residuals:Arrows2D:vectors")
        counts = [len(residuals.get(f, [])) for f in range(FRAMES)]
        assert set(counts) <= {0, CORNERS}  # one arrow per corner of that frame's board, none of other frames'
        assert sum(counts) == calib.metrics["frames_per_view"][names.index(name)] * CORNERS
        rms = last_per_frame(rows, f"/rms/{name}:Scalars:scalars")
        assert len(rms) == calib.metrics["frames_per_view"][names.index(name)]
    # optimiser: error and RMS are separate, named series and bar charts with one bar per iteration
    assert static["/optimizer/error:SeriesLines:names"][0] != static["/optimizer/rms_px:SeriesLines:names"][0]
    assert static["/optimizer/error:SeriesLines:colors"][0] != static["/optimizer/rms_px:SeriesLines:colors"][0]
    # one chart per stage: a calibration's iterations are its joint stage's (the one schedule names it; the screen's
    # robust fit is not heard)
    charts = [c for c in columns if c.startswith("/optimizer_summary/rms_px/") and c.endswith(":BarChart:values")]
    assert charts == ["/optimizer_summary/rms_px/joint:BarChart:values"]
    bars = static["/optimizer_summary/rms_px/joint:BarChart:abscissa"][0][0]["buffer"]
    assert len(bars) == calib.metrics["iterations"] > 0
    _, _, by_iteration = read_rrd(rrd, "iteration")
    steps = [x for x in by_iteration["/optimizer/error:Scalars:scalars"] if x is not None]
    assert len(steps) == calib.metrics["iterations"]


def assert_corners_on_own_images(rrd, calib) -> None:
    """The corners logged on a frame are where OpenCV finds the board in the image logged on that frame."""
    import cv2

    _, _, rows = read_rrd(rrd, "frame")
    checked = 0
    for v in range(calib.num_views):
        name = calib.grid.name(v)
        images = last_per_frame(rows, f"/views/{name}/image:EncodedImage:blob")
        assert sorted(images) == list(range(FRAMES)), name  # every frame has its images
        observed = last_per_frame(rows, f"/views/{name}/observed:Points2D:positions")
        for f, blob in images.items():
            image = cv2.imdecode(np.asarray(blob[0], dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
            found, corners = cv2.findChessboardCorners(image, (7, 5))
            if not found or len(observed.get(f, [])) != CORNERS:
                continue
            logged = np.asarray(observed[f])
            gap_px = np.linalg.norm(corners.reshape(-1, 1, 2) - logged[None], axis=-1).min(axis=1)
            assert np.median(gap_px) < JPEG_CORNER_TOLERANCE_PX, (name, f)  # another frame's board: tens of px
            checked += 1
    assert checked >= FRAMES  # most view-frames show a whole board


def test_each_frame_shows_its_own_corners_on_its_own_image(calibrated):
    assert_corners_on_own_images(*calibrated)


@pytest.mark.slow
def test_api_calibration_records_its_images_and_layout(board_capture, tmp_path):
    """Issue 40: ``lf.calibrate(obs, observer=rec)`` recorded no image. The logger, given neither grid, kind nor
    frames, finds the images in the files the corners were detected in, each frame's own, and the recording opens
    in calibrate's layout with the eye on the calibrated rig."""
    import lfgraph as lf
    from lfgraph.viz import RerunLogger

    capture = lf.open_capture(board_capture, lf.ViewGrid(2, 2, 0))
    obs, _ = lf.detect_capture(capture, lf.BoardSpec.parse("7x5", 15.0), jobs=1, progress=False)
    rrd = tmp_path / "api.rrd"
    with RerunLogger.to_file(rrd) as rec:
        calib, _ = lf.calibrate(obs, observer=rec)
    assert_corners_on_own_images(rrd, calib)
    eye = []
    views, timeline = read_blueprint(rrd, eye)
    assert timeline == "frame" and ("TextLog", "log") in {(k, o) for k, o, _ in views}
    width, _, reach = view_share(eye[0], calib.ref_T_view[:, :3, 3])
    assert width >= RIG_MIN_WIDTH_SHARE and reach <= 1, (width, reach)


def test_calibrate_blueprint(calibrated):
    rrd, calib = calibrated
    views, timeline = read_blueprint(rrd)
    assert timeline == "frame"
    kinds = {(k, o) for k, o, _ in views}
    assert ("3D", "world") in kinds and ("TimeSeries", "rms") in kinds
    assert {o for k, o in kinds if k == "2D"} == {f"views/{calib.grid.name(v)}" for v in range(calib.num_views)}
    assert sum(k == "BarChart" for k, _ in kinds) == 2  # error and RMS each in its own view
    columns, _, _ = read_rrd(rrd, "frame")
    assert_every_view_has_data(views, columns)


def test_outlier_frame_in_red_on_its_frame(board_capture, tmp_path):
    from lfgraph.core.grid import ViewGrid
    from lfgraph.detect.board import BoardSpec
    from lfgraph.detect.detections import detect_capture
    from lfgraph.io.capture import open_capture
    from lfgraph.pattern import calibrate
    from lfgraph.viz import RerunLogger

    grid = ViewGrid(2, 2, 0)
    capture = open_capture(board_capture, grid, "auto")
    obs, _ = detect_capture(capture, BoardSpec.parse("7x5", 15.0), jobs=1, progress=False)
    calib, report = calibrate(obs)
    outlier = 3
    report = dataclasses.replace(report, outlier_frames=(outlier,))
    rrd = tmp_path / "o.rrd"
    with RerunLogger.to_file(rrd, grid) as logger:
        logger.calibration_result(calib, obs, report, capture.load_frame)
    _, _, rows = read_rrd(rrd, "frame")
    red = last_per_frame(rows, "/views/r00_c00/outliers:Points2D:positions")
    assert len(red[outlier]) == obs.valid[0, outlier].sum() > 0
    assert all(len(red[f]) == 0 for f in red if f != outlier)  # nothing lingers on the other frames
    np.testing.assert_allclose(np.array(red[outlier]), obs.corners_px[0, outlier][obs.valid[0, outlier]], atol=1e-3)


@pytest.mark.slow
def test_refine_recording(scene, tmp_path):
    rrd, out = tmp_path / "refine.rrd", tmp_path / "r.json"
    assert main(["refine", str(scene / "original.json"), str(scene), "-o", str(out), "--quiet",
                 "--save", str(rrd)]) == 0
    refined, original = Calibration.load(out), Calibration.load(scene / "original.json")
    m = refined.metrics["refinement"]
    columns, static, rows = read_rrd(rrd, "frame")
    assert static["/world:ViewCoordinates:xyz"][0] == [RDF]
    for v in range(refined.num_views):
        name = refined.grid.name(v)
        for rig, calib in (("input_rig", original), ("refined_rig", refined)):
            np.testing.assert_allclose(static[f"/world/{rig}/{name}:Transform3D:translation"][0][0],
                                       calib.ref_T_view[v][:3, 3], atol=1e-9)
    assert static["/world/input_rig/r00_c01:Pinhole:color"] != static["/world/refined_rig/r00_c01:Pinhole:color"]
    # each 2-D view is a camera of the 3-D scene at the refined pose: its images sit in its frustum (issue 28)
    for v in range(refined.num_views):
        name = refined.grid.name(v)
        np.testing.assert_allclose(static[f"/views/{name}:Transform3D:translation"][0][0],
                                   refined.ref_T_view[v][:3, 3], atol=1e-9)
        assert static[f"/views/{name}:Pinhole:image_from_camera"][0] is not None
    labels = static["/world/change:Arrows3D:labels"][0]
    # one short label per view, naming it (issue 28: a 5x5's 25 long labels overlapped)
    assert [s.split()[0].rstrip(":") for s in labels] == [refined.grid.name(v) for v in range(refined.num_views)]
    ref = refined.grid.reference
    assert "arrows x" in labels[ref] and all(len(s) <= CHANGE_LABEL_CHARS for s in labels), labels
    assert all("°" in s and "mm" in s for v, s in enumerate(labels) if v != ref), labels
    assert not np.allclose(refined.ref_T_view, original.ref_T_view)  # the shake was refined: the rigs differ
    # per frame: that frame's image and tracks
    images = last_per_frame(rows, "/views/r01_c01/image:EncodedImage:blob")
    assert sorted(images) == [0, 1] and images[0] != images[1]
    tracks = last_per_frame(rows, "/views/r01_c01/residuals:Arrows2D:vectors")
    assert len(tracks[0]) > 0 and len(tracks[1]) > 0
    observed = last_per_frame(rows, "/views/r01_c01/observed:Points2D:positions")
    assert not {tuple(p) for p in observed[0]} & {tuple(p) for p in observed[1]}  # no track drawn on both frames
    red = last_per_frame(rows, "/views/r01_c01/outliers:Points2D:positions")
    assert any(len(p) for p in red.values())  # filtered tracks, in red on their frame
    landmarks = [x for x in rows["/world/landmarks:Points3D:positions"] if x is not None]
    assert len(landmarks[-1]) == m["stages"][-1]["landmarks"]
    _, _, by_iteration = read_rrd(rrd, "iteration")
    assert len([x for x in by_iteration["/optimizer/error:Scalars:scalars"] if x is not None]) \
        == m["total_iterations"] > 0
    assert len([x for x in by_iteration["/optimizer/stages:TextLog:text"] if x is not None]) == 2 * 3
    # the RMS chart is in pixels: its last value is the last stage's RMS (priors add a little), not that RMS over
    # the measurement sigma (~0.05 px, which plotted 4.30 for 0.215 px)
    rms = [x[0] for x in by_iteration["/optimizer/rms_px:Scalars:scalars"] if x is not None]
    assert rms[-1] == pytest.approx(m["stages"][-1]["rms_after_px"], rel=RMS_CHART_REL)
    # the error chart: one chart per stage name (the legend names them), a bar per iteration, 0..3 decades
    stages = {c.split("/")[3].split(":")[0] for c in columns if c.startswith("/optimizer_summary/error_decades/")}
    assert stages == {st["name"] for st in m["stages"]}, stages
    decades = np.concatenate([static[f"/optimizer_summary/error_decades/{name}:BarChart:values"][0][0]["buffer"]
                              for name in stages])
    assert len(decades) == m["total_iterations"] and decades.min() >= 0 and decades.max() <= MAX_DECADES
    # ... each stage's bars in one colour of its own, the colour of the lines saying where it starts
    colours = {name: static[f"/optimizer_summary/error_decades/{name}:BarChart:color"][0] for name in stages}
    assert len({str(c) for c in colours.values()}) == len(stages)
    lines = by_iteration["/optimizer/stages:TextLog:text"], by_iteration["/optimizer/stages:TextLog:color"]
    for text, colour in zip(*lines, strict=True):
        if text is not None:
            assert colour == colours[text[0].split()[3]], text
    eye = []
    views, timeline = read_blueprint(rrd, eye)
    assert timeline == "frame"
    assert ("TextLog", "optimizer/stages") in {(k, o) for k, o, _ in views}
    # the 3-D view opens on the rig (not on landmarks metres away): the input rig (the first logged) fills the view
    width, _, reach = view_share(eye[0], original.ref_T_view[:, :3, 3])
    assert width >= RIG_MIN_WIDTH_SHARE and reach <= 1, (width, reach)
    assert np.linalg.norm(eye[0][1] - eye[0][0]) < np.linalg.norm(landmarks[-1], axis=1).min()
    assert_every_view_has_data(views, columns)


@pytest.mark.slow
def test_api_refinement_opens_in_refine_layout_and_never_pairs_frames(scene, tmp_path):
    """Issue 40: the README's ``RerunLogger.to_file(path, grid)`` around ``lf.refine`` opened calibrate's layout
    (no stages panel). The layout follows the run. And while a recording loads, a frame's images never show the
    last frame's tracks: the points are emptied with the images, before the frame's first stage ends."""
    import lfgraph as lf
    from lfgraph.viz import RerunLogger

    calib = lf.Calibration.load(scene / "original.json")
    capture = lf.open_capture(scene, calib.grid)
    rrd = tmp_path / "api.rrd"
    with RerunLogger.to_file(rrd, calib.grid) as rec:
        lf.refine(calib, capture.frames(), observer=rec)
    eye = []
    views, _ = read_blueprint(rrd, eye)
    assert ("TextLog", "optimizer/stages") in {(k, o) for k, o, _ in views}
    width, _, reach = view_share(eye[0], calib.ref_T_view[:, :3, 3])
    assert width >= RIG_MIN_WIDTH_SHARE and reach <= 1, (width, reach)
    observed = stream_rows(rrd, "/views/r01_c01/observed", "Points2D:positions")
    first_at = {}
    for f, points in observed:
        first_at.setdefault(f, points)
    assert sorted(first_at) == [0, 1] and first_at[1] == []  # frame 1 starts empty...
    assert len([p for f, p in observed if f == 1][-1]) > 0  # ... and ends with its own tracks


def test_rectify_recording(scene, tmp_path):
    rrd = tmp_path / "rect.rrd"
    assert main(["rectify", str(scene / "original.json"), str(scene), "-o", str(tmp_path / "out"), "--quiet",
                 "--jobs", "1", "--save", str(rrd)]) == 0
    columns, static, _ = read_rrd(rrd, None)  # all static: no timeline
    views, _ = read_blueprint(rrd)
    grid_views = {o for k, o, _ in views if k == "2D"}
    assert grid_views == {f"rectified/r{r:02d}_c{c:02d}" for r in range(2) for c in range(2)}
    for origin in grid_views:
        assert static[f"/{origin}/image:EncodedImage:blob"][0]
        assert len(static[f"/{origin}/guides:LineStrips2D:strips"][0]) > 1
    assert_every_view_has_data(views, columns)


@pytest.mark.slow
def test_stdout_is_a_valid_stream_and_reports_go_to_stderr(scene, tmp_path):
    rrd = tmp_path / "stream.rrd"
    with rrd.open("wb") as fh:
        done = subprocess.run([sys.executable, "-m", "lfgraph", "refine", str(scene / "original.json"), str(scene),
                               "-o", str(tmp_path / "r.json"), "--quiet", "--max-frames", "1", "--stdout"],
                              stdout=fh, stderr=subprocess.PIPE, text=True, check=True, timeout=300)
    assert "wrote" in done.stderr and "RMS" in done.stderr
    columns, static, _ = read_rrd(rrd, "frame")
    assert static["/world:ViewCoordinates:xyz"][0] == [RDF]
    assert any(c.startswith("/world/refined_rig/") for c in columns)


def test_no_flags_no_recording(board_capture, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["calibrate", str(board_capture), *SMALL, "-o", str(tmp_path / "c.json")]) == 0
    assert not list(tmp_path.glob("*.rrd")) and rr.get_global_data_recording() is None


@pytest.mark.parametrize("target", ["missing/dir/run.rrd", "."])
def test_unwritable_save_path_fails_before_work(board_capture, tmp_path, capsys, target):
    out = tmp_path / "c.json"
    with pytest.raises(SystemExit) as exc:
        main(["calibrate", str(board_capture), *SMALL, "-o", str(out), "--save", str(tmp_path / target)])
    assert exc.value.code == 2
    assert "--save" in capsys.readouterr().err
    assert not out.exists()


def test_blueprint_kinds_are_checked():
    from lfgraph.core.grid import ViewGrid
    from lfgraph.viz import default_blueprint

    with pytest.raises(ValueError, match="unknown blueprint"):
        default_blueprint(ViewGrid(2, 2, 0), "plot")


def test_a_logger_of_an_unknown_kind_fails_at_once_and_leaves_nothing(tmp_path):
    from lfgraph.core.grid import ViewGrid
    from lfgraph.viz import RerunLogger

    with pytest.raises(ValueError, match="unknown blueprint"):
        RerunLogger.to_file(tmp_path / "x.rrd", ViewGrid(2, 2, 0), "plot")
    assert not list(tmp_path.iterdir())



@pytest.mark.slow
def test_stdout_to_a_reader_that_goes_away_neither_hangs_nor_loses_the_result(scene, tmp_path):
    """Issue 27: `--stdout | head -c 100` never exited and wrote no calibration."""
    out = tmp_path / "r.json"
    cmd = [sys.executable, "-m", "lfgraph", "refine", str(scene / "original.json"), str(scene), "-o", str(out),
           "--quiet", "--max-frames", "1", "--stdout"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.read(100)  # the reader takes 100 bytes and goes away, as `| head -c 100` does
    proc.stdout.close()
    _, err = proc.communicate(timeout=STDOUT_CLOSED_S)
    assert proc.returncode == 1 and b"stopped reading" in err
    assert out.exists()  # the command's own output was written
