"""Inputs and outputs a user can trust (issue 19): no command destroys its input, bad outputs fail before the work,
nothing is left behind by a killed run, and damaged files give messages instead of tracebacks."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from lfgraph.cli import EXIT_BAD_INPUT, EXIT_INTERNAL, EXIT_OK, EXIT_USAGE, main
from lfgraph.cli.tables import alignment_table
from lfgraph.core.calibration import Calibration, CalibrationFileError
from lfgraph.datasets.rig import RigConfig, make_rig
from lfgraph.rectification.rectify import RectificationError, compute_rectification

pytestmark = pytest.mark.slow  # end-to-end runs (`make test-fast` leaves them out)

ROOT = Path(__file__).resolve().parents[2]
SMALL = ["--grid", "2x2", "--board", "7x5", "--square-mm", "15", "--jobs", "2", "--quiet"]
WORKER_EXIT_S = 10.0  # orphaned pool workers must be gone within this after their parent is killed


@pytest.fixture(scope="module")
def boards(tmp_path_factory):
    out = tmp_path_factory.mktemp("safety") / "boards"
    assert main(["synth", "checkerboard", str(out), "--scene", "small-2x2", "--frames", "6", "--jobs", "2",
                 "--quiet"]) == 0
    return out


def run(args, capsys):
    try:
        code = main([str(a) for a in args])
    except SystemExit as exc:  # argparse's usage errors
        code = exc.code
    captured = capsys.readouterr()
    return code, captured.out + captured.err


def test_calibrate_refuses_to_write_over_an_input_image(boards, capsys):
    image = next(boards.glob("*/r00_c00.png"))
    before = image.read_bytes()
    code, text = run(["calibrate", boards, *SMALL, "-o", image], capsys)
    assert code == EXIT_BAD_INPUT and str(image) in text and "refusing to overwrite" in text
    assert image.read_bytes() == before


def test_refine_refuses_its_inputs_and_overwrites_a_calibration_only_when_asked(boards, tmp_path, capsys):
    calib = boards / "truth.json"
    image = next(boards.glob("*/r00_c00.png"))
    before = calib.read_bytes(), image.read_bytes()
    for target in (calib, image):
        code, text = run(["refine", calib, boards, "-o", target, "--quiet"], capsys)
        assert code == EXIT_BAD_INPUT and str(target) in text
    assert (calib.read_bytes(), image.read_bytes()) == before
    assert "--overwrite" in run(["refine", calib, boards, "-o", calib, "--quiet"], capsys)[1]


def test_save_and_plots_follow_the_output_rule(boards, tmp_path, capsys):
    """Issue 27: `--save` and `--plots` were not checked like `-o`: a recording replaced the input calibration or an
    image, `--plots` into the capture made it ambiguous, and a study's figure replaced its CSV."""
    calib = boards / "truth.json"
    image = next(boards.glob("*/r00_c00.png"))
    listing = sorted(p.name for p in boards.rglob("*"))
    before = calib.read_bytes(), image.read_bytes()
    for target in (calib, image):
        code, text = run(["refine", calib, boards, "-o", tmp_path / "r.json", "--save", target, "--quiet"], capsys)
        assert code == EXIT_BAD_INPUT and "--save" in text and str(target) in text
    code, text = run(["refine", calib, boards, "-o", tmp_path / "r.json", "--save", tmp_path / "r.json", "--quiet"],
                     capsys)
    assert code == EXIT_USAGE and "--save" in text and "also the command's output" in text
    code, text = run(["calibrate", boards, *SMALL, "-o", tmp_path / "c.json", "--plots", boards], capsys)
    assert code == EXIT_BAD_INPUT and "--plots" in text and "inside the input" in text
    code, text = run(["calibrate", boards, *SMALL, "-o", tmp_path / "c.json", "--plots", boards / "figs"], capsys)
    assert code == EXIT_BAD_INPUT and "inside the input" in text
    assert (calib.read_bytes(), image.read_bytes()) == before
    assert sorted(p.name for p in boards.rglob("*")) == listing  # nothing was written into the capture
    assert not (tmp_path / "r.json").exists() and not (tmp_path / "c.json").exists()
    code, text = run(["study", "shake", "--scene", "small-2x2", "--trials", "1", "-o", tmp_path / "s.png",
                      "--quiet"], capsys)
    assert code == EXIT_USAGE and ".csv" in text and not (tmp_path / "s.png").exists()


def test_synth_never_mixes_two_data_sets_and_non_regular_outputs_are_refused(tmp_path, capsys):
    out = tmp_path / "scene"
    args = ["synth", "scene", out, "--scene", "small-2x2", "--frames", "2", "--jobs", "1", "--quiet"]
    assert run(args, capsys)[0] == EXIT_OK
    frames_before = sorted(p.name for p in out.iterdir())
    code, text = run([*args[:-3], "--frames", "1", "--jobs", "1", "--quiet"], capsys)
    assert code == EXIT_USAGE and "--overwrite" in text
    assert sorted(p.name for p in out.iterdir()) == frames_before  # untouched
    assert run([*args[:-3], "--frames", "1", "--jobs", "1", "--quiet", "--overwrite"], capsys)[0] == EXIT_OK
    assert len([p for p in out.iterdir() if p.is_dir()]) == 1  # emptied first: no frame of the old set is left
    other = tmp_path / "notes"
    other.mkdir()
    (other / "mine.txt").write_text("keep me")
    code, text = run(["synth", "scene", other, "--scene", "small-2x2", "--frames", "1", "--quiet", "--overwrite"],
                     capsys)
    assert code == EXIT_USAGE and "not a synthetic set" in text and (other / "mine.txt").read_text() == "keep me"
    # a symlink or a FIFO given as -o is refused, not replaced by a regular file
    target = tmp_path / "real.json"
    target.write_text("{}")
    link = tmp_path / "link.json"
    link.symlink_to(target)
    fifo = tmp_path / "fifo.json"
    os.mkfifo(fifo)
    for bad, what in ((link, "symbolic link"), (fifo, "not a regular file")):
        code, text = run(["refine", out / "truth.json", out, "-o", bad, "--quiet"], capsys)
        assert code == EXIT_BAD_INPUT and what in text
    assert link.is_symlink() and target.read_text() == "{}" and fifo.is_fifo()


def test_an_internal_failure_is_said_as_such_not_as_bad_input(boards, tmp_path, capsys, monkeypatch):
    """Issue 27: GTSAM's IndeterminateSystemException reached the user raw, as exit 1 "bad input". The threshold that
    caused it (tukey:0.0001) is now refused before the work; a failure inside lfgraph is still exit 4."""
    code, text = run(["calibrate", boards, *SMALL, "--robust", "tukey:0.0001", "-o", tmp_path / "c.json"], capsys)
    assert code in (EXIT_BAD_INPUT, EXIT_USAGE) and "threshold must be a number from" in text

    def broken(*_args, **_kwargs):
        raise RuntimeError("Indeterminant linear system detected while working near variable 7")

    monkeypatch.setattr("lfgraph.pattern.schedule.calibrate_joint", broken)  # lfgraph's own code, not a library
    code, text = run(["calibrate", boards, *SMALL, "-o", tmp_path / "c.json"], capsys)
    assert code == EXIT_INTERNAL and "internal error" in text and "report" in text
    assert not (tmp_path / "c.json").exists()


def test_connect_without_a_viewer_fails_before_the_work(boards, tmp_path, capsys):
    """Issue 27: `--connect` with no viewer ran the whole command, waited 71 s after writing, then exited 1."""
    import socket

    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    start = time.perf_counter()
    code, text = run(["refine", boards / "truth.json", boards, "-o", tmp_path / "r.json", "--quiet", "--connect",
                      "--url", f"rerun+http://127.0.0.1:{port}/proxy"], capsys)
    assert code == EXIT_USAGE and "no rerun viewer listens" in text
    assert time.perf_counter() - start < 5.0 and not (tmp_path / "r.json").exists()


def test_outputs_that_cannot_be_written_fail_before_any_work(boards, tmp_path, capsys):
    start = time.perf_counter()
    code, text = run(["calibrate", boards, *SMALL, "-o", tmp_path], capsys)  # a folder
    assert code == EXIT_USAGE and "is a folder" in text
    code, text = run(["calibrate", boards, *SMALL, "-o", tmp_path / "missing" / "c.json"], capsys)
    assert code == EXIT_USAGE and "does not exist" in text
    code, text = run(["rectify", boards / "truth.json", boards, "-o", boards / "inside"], capsys)
    assert code == EXIT_USAGE and "inside the input" in text
    assert time.perf_counter() - start < 5.0  # no detection ran (it takes longer than this on these images)


def test_absurd_image_size_and_huge_numbers_give_messages(tmp_path, capsys):
    code, text = run(["synth", "scene", tmp_path / "x", "--image-size", "1000000x1000000"], capsys)
    assert code == EXIT_USAGE and "larger than any camera" in text
    calib = make_rig(RigConfig(rows=1, cols=2), np.random.default_rng(0))
    data = calib.to_dict()
    data["views"][0]["K"][0][0] = 10**400
    path = tmp_path / "big.json"
    path.write_text(json.dumps(data))
    with pytest.raises(CalibrationFileError, match=r"big.json.*K.*out of range"):
        Calibration.load(path)


def test_a_corrupt_detection_cache_is_rebuilt_with_a_warning(boards, tmp_path, capsys):
    out = tmp_path / "c.json"
    assert run(["calibrate", boards, *SMALL, "-o", out], capsys)[0] == EXIT_OK
    cache = boards / ".lfgraph-detections.npz"
    assert cache.exists()
    cache.write_bytes(b"not a zip file")
    code, text = run(["calibrate", boards, *SMALL, "-o", out], capsys)
    assert code == EXIT_OK and "unreadable detection cache" in text
    assert cache.read_bytes()[:2] == b"PK"  # rewritten as a valid npz


def test_a_truncated_study_csv_reruns_the_cut_rows(tmp_path, capsys):
    csv = tmp_path / "cal.csv"
    args = ["study", "calibration", "--scene", "small-2x2", "--frames", "5", "--sigma-px", "0.1", "--trials", "1",
            "--jobs", "1", "--quiet", "-o", csv]
    assert run(args, capsys)[0] == EXIT_OK
    full = csv.read_text()
    csv.write_text(full[: len(full) - 15])  # the last row cut short
    code, text = run(args, capsys)
    assert code == EXIT_OK and "incomplete row" in text
    assert csv.read_text() == full


def test_rectify_refuses_views_that_barely_overlap():
    calib = make_rig(RigConfig(rows=1, cols=2, image_size_px=(320, 240), focal_px=300.0), np.random.default_rng(0))
    turned = calib.ref_T_view.copy()
    angle = np.radians(53.0)  # the second view looks 53 degrees to the side: a sliver of common view (was -3x-3 px)
    turned[1, :3, :3] = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    with pytest.raises(RectificationError, match="barely overlap"):
        compute_rectification(calib.replace(ref_T_view=turned), "valid")


def test_alignment_table_of_a_stereo_pair_says_what_it_lacks():
    from lfgraph.judge.alignment import Alignment

    text = alignment_table([("rectified", Alignment(0.2, float("nan"), float("nan"), 120, 0, 0))])
    assert "nan" not in text and "needs 3+ views" in text and "120" in text


# ------------------------------------------------------------------------------------------------ killed runs
def _children(pid: int) -> list[int]:
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(entry.name))
    return out


def _running(pid: int) -> bool:
    try:
        state = (Path("/proc") / str(pid) / "stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state not in ("Z", "X")  # a zombie has exited


def _kill_when_workers_run(cmd: list[str], cwd: Path) -> list[int]:
    """Start ``cmd``, wait for its pool workers, kill -9 the parent; returns the workers' pids."""
    proc = subprocess.Popen([sys.executable, "-m", "lfgraph", *cmd], cwd=cwd, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    workers: list[int] = []
    while time.monotonic() < deadline and proc.poll() is None:
        workers = _children(proc.pid)
        if len(workers) >= 2:
            break
        time.sleep(0.05)
    assert proc.poll() is None and workers, "the command finished before its workers could be seen"
    time.sleep(0.5)  # let them start working
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    return workers


def _wait_gone(pids: list[int]) -> list[int]:
    deadline = time.monotonic() + WORKER_EXIT_S
    while time.monotonic() < deadline:
        alive = [p for p in pids if _running(p)]
        if not alive:
            return []
        time.sleep(0.1)
    return [p for p in pids if _running(p)]


def test_killed_rectify_leaves_no_worker_and_the_next_run_cleans_its_partial_folder(tmp_path):
    calib = make_rig(RigConfig(rows=2, cols=2, image_size_px=(1024, 768), focal_px=800.0), np.random.default_rng(0))
    calib.save(tmp_path / "calib.json")
    yy, xx = np.mgrid[0:768, 0:1024]
    for f in range(40):
        for name in ("r00_c00", "r00_c01", "r01_c00", "r01_c01"):
            image = (127 + 100 * np.sin(xx / (20 + f)) * np.cos(yy / 30)).astype(np.uint8)
            (tmp_path / "cap" / f"{f:03d}").mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(tmp_path / "cap" / f"{f:03d}" / f"{name}.jpg"), image)
    cmd = ["rectify", "calib.json", "cap", "-o", "out", "--jobs", "2", "--quiet"]
    workers = _kill_when_workers_run(cmd, tmp_path)
    assert _wait_gone(workers) == []
    assert not (tmp_path / "out").exists()
    assert list(tmp_path.glob(".out.*")), "a killed run cannot clean up; the next run must"
    done = subprocess.run([sys.executable, "-m", "lfgraph", *cmd], cwd=tmp_path, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert not list(tmp_path.glob(".out.*")) and len(list((tmp_path / "out").iterdir())) == 41


def test_killed_study_leaves_no_worker(tmp_path):
    cmd = ["study", "calibration", "--scene", "small-2x2", "--frames", "4,8", "--sigma-px", "0.1,0.3",
           "--trials", "6", "--jobs", "2", "--quiet", "-o", "s.csv"]
    workers = _kill_when_workers_run(cmd, tmp_path)
    assert _wait_gone(workers) == []


def test_a_guessed_layout_is_said_and_a_wrong_grid_is_summarised(tmp_path, capsys):
    for name in ("im0.png", "im1.png"):  # Middlebury-style names match no layout
        cv2.imwrite(str(tmp_path / name), np.zeros((100, 301), np.uint8))
    code, text = run(["calibrate", tmp_path, *SMALL, "-o", tmp_path / "c.json"], capsys)
    assert code == EXIT_BAD_INPUT and "layout guessed as 'mosaic'" in text and "--layout" in text
    frame = tmp_path / "frames" / "000"
    frame.mkdir(parents=True)
    for name in ("r00_c00", "r00_c01"):
        cv2.imwrite(str(frame / f"{name}.png"), np.zeros((24, 32), np.uint8))
    code, text = run(["calibrate", tmp_path / "frames", "--grid", "1000x1000", "--board", "7x5", "--square-mm", "15",
                      "-o", tmp_path / "c.json"], capsys)
    assert code == EXIT_BAD_INPUT and "check --grid" in text and len(text) < 2000


# ------------------------------------------------------------------------------------------- interrupted runs
def test_a_command_stopped_late_leaves_none_of_its_outputs(boards, tmp_path, capsys, monkeypatch):
    """Ctrl-C after the calibration, the recording and the first figure were written: none stays (a half set of
    outputs)."""
    from lfgraph.core.files import write_bytes_atomic
    from lfgraph.viz import figures

    def first_figure_then_ctrl_c(calib, obs, report, out_dir):
        write_bytes_atomic(Path(out_dir) / "coverage.png", b"\x89PNG")
        raise KeyboardInterrupt

    monkeypatch.setattr(figures, "calibration_report_figures", first_figure_then_ctrl_c)
    out, plots = tmp_path / "o.json", tmp_path / "figs" / "run1"
    code, text = run(["calibrate", boards, "--grid", "2x2", "--board", "7x5", "--square-mm", "15", "-o", out,
                      "--plots", plots, "--save", tmp_path / "r.rrd", "--quiet"], capsys)
    assert code == 130 and "interrupted" in text
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # o.json, r.rrd, figs/run1/coverage.png, folders: gone


def test_an_interrupted_synth_leaves_no_partial_folder(tmp_path):
    """Ctrl-C while frames are being rendered: the set appears whole or not at all (it is rendered beside its
    final name, in a hidden temporary folder, and renamed into place at the end)."""
    proc = subprocess.Popen([sys.executable, "-m", "lfgraph", "synth", "scene", "scene", "--scene", "small-2x2",
                             "--frames", "40", "--jobs", "1", "--quiet"], cwd=tmp_path, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None and not list(tmp_path.glob(".scene.*/001")):
        time.sleep(0.05)
    assert proc.poll() is None, "the render finished before it could be interrupted"
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "interrupted" in err
    assert list(tmp_path.iterdir()) == []


def test_the_demo_replaces_only_its_own_folder(tmp_path, capsys):
    out = tmp_path / "demo"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    code, text = run(["demo", "--scene", "small-2x2", "--out", out, "--no-refine", "--quiet"], capsys)
    assert code == EXIT_BAD_INPUT and "notes.txt" in text and (out / "notes.txt").read_text() == "mine"
