"""The ``lfgraph`` program's processes, signals and streams, and the faults an independent trial of bad inputs found:
a killed run releases a caller that reads its pipes at once (its pool workers and fork server die with it), Ctrl-C
at any instant is a clean exit 130, closed standard streams are not an error and a reader that goes away ends the
run with 141, a FIFO in place of the detection cache or the fleet manifest is never read, a fleet run leaves no
temporary file and a failed one nothing new, and rotations printed to 6 decimals load.

Every run is a real process (``python -m lfgraph``, the program's own entry) in a session of its own, bounded by a
timeout, and killed with its whole session if a regression makes it hang."""

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

LFG = [sys.executable, "-m", "lfgraph"]
BOARD = ["--grid", "2x2", "--board", "7x5", "--square-mm", "15"]
RUN_S = 120.0  # any run of this file ends within this, or the test fails (it never hangs)
RELEASE_S = 5.0  # a caller of a killed run reads the end of its pipes within this (measured: 0.03 s)
GONE_S = 10.0  # the processes of a stopped run are gone (zombies aside: they hold nothing) within this
WORKERS_S = 60.0  # a run's pool workers have started within this
EXIT_INTERRUPTED, EXIT_READER_GONE = 130, 141
# a rotation as HALCON (and many tools) print it, to 6 decimals: R^T R is I only to 1.5e-6
R_6_DECIMALS = [[0.844693, 0.189133, -0.500721], [-0.073738, 0.967689, 0.241124], [0.530147, -0.166754, 0.831346]]
ORTHONORMAL_EXACT = 1e-12  # a re-orthonormalised rotation is orthonormal to rounding
PRINTED_PRECISION = 1e-5  # and differs from the printed matrix by about the printing's error


# ------------------------------------------------------------------------------------------------ helpers
def _stat(pid: int) -> list[str] | None:
    """Fields of /proc/PID/stat after the command name (state, ppid, pgrp, session, ...), None when gone."""
    try:
        return (Path("/proc") / str(pid) / "stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None


def _session(sid: int) -> list[int]:
    """Processes of session ``sid`` that still run (a zombie has ended: it holds no file or pipe)."""
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            fields = _stat(int(entry.name))
            if fields is not None and int(fields[3]) == sid and fields[0] not in ("Z", "X"):
                out.append(int(entry.name))
    return out


def _wait_session_gone(sid: int) -> list[int]:
    deadline = time.monotonic() + GONE_S
    while time.monotonic() < deadline and _session(sid):
        time.sleep(0.05)
    return _session(sid)


def _start(args: list, cwd: Path, **kw) -> subprocess.Popen:
    kw.setdefault("stdout", subprocess.DEVNULL)
    kw.setdefault("stderr", subprocess.PIPE)
    return subprocess.Popen([*LFG, *map(str, args)], cwd=cwd, stdin=subprocess.DEVNULL, start_new_session=True,
                            **kw)


def _end_session(proc: subprocess.Popen) -> None:
    """After the test: nothing of the run may survive it, whatever happened (a regression must not hang pytest)."""
    for pid in _session(proc.pid):
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    if proc.poll() is None:
        proc.kill()
        proc.wait(RUN_S)


def _wait_for(proc: subprocess.Popen, what: str) -> list[int]:
    """The run's fork server (``what="server"``: its child that runs multiprocessing's fork server) or pool workers
    (``"workers"``: its grandchildren, children of the fork server), once there are some."""
    deadline = time.monotonic() + WORKERS_S
    while time.monotonic() < deadline and proc.poll() is None:
        children = {pid for pid in _session(proc.pid) if (_stat(pid) or ["", "0"])[1] == str(proc.pid)}
        if what == "server":
            found = [pid for pid in children if b"forkserver" in _cmdline(pid)]
        else:
            found = [pid for pid in _session(proc.pid) if int((_stat(pid) or ["", "0"])[1]) in children]
        if found:
            return found
        time.sleep(0.005)
    pytest.fail(f"the run ended before its {what} could be seen")


def _cmdline(pid: int) -> bytes:
    try:
        return (Path("/proc") / str(pid) / "cmdline").read_bytes()
    except OSError:
        return b""


def _lfgraph(args: list, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([*LFG, *map(str, args)], cwd=cwd, capture_output=True, text=True, timeout=RUN_S)


def _listing(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*")}


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """40 frames of a 2x2 board capture (long enough to be stopped halfway with 2 workers) and its calibration."""
    root = tmp_path_factory.mktemp("processes")
    done = _lfgraph(["synth", "checkerboard", "cb", "--scene", "small-2x2", "--frames", "40", "--jobs", "2",
                     "--quiet"], root)
    assert done.returncode == 0, done.stderr
    done = _lfgraph(["calibrate", "cb", *BOARD, "--jobs", "2", "--quiet", "-o", "cal.json"], root)
    assert done.returncode == 0, done.stderr
    (root / "cb" / ".lfgraph-detections.npz").unlink()
    return root


def _argv(command: str, data: Path) -> list:
    return {"calibrate": ["calibrate", data / "cb", *BOARD, "--no-cache", "--jobs", "2", "-o", "o.json"],
            "rectify": ["rectify", data / "cal.json", data / "cb", "--jobs", "2", "-o", "rect"],
            "synth": ["synth", "checkerboard", "out", "--scene", "small-2x2", "--frames", "40", "--jobs", "2"]}[command]


# ------------------------------------------------------------------------------------------------ killed runs
@pytest.mark.slow
@pytest.mark.parametrize(("command", "when"), [("calibrate", "workers"), ("rectify", "workers"),
                                               ("synth", "workers"), ("calibrate", "server")])
def test_a_killed_run_releases_a_caller_that_reads_its_pipes(command, when, data, tmp_path):
    """The bounded run of Python's documentation: ``communicate(timeout)``, then ``kill()`` and ``communicate()``.
    The second ``communicate`` waited forever: the pool workers and the fork server, which hold the run's pipes,
    watched the killed parent with ``os.kill(pid, 0)``, which a zombie passes. Killed once the workers run, or as
    soon as the fork server starts (before it could arm its parent-death signal)."""
    proc = _start([*_argv(command, data), "--quiet"], tmp_path, stdout=subprocess.PIPE)
    try:
        _wait_for(proc, when)
        if when == "workers":
            with pytest.raises(subprocess.TimeoutExpired):
                proc.communicate(timeout=0.2)
        proc.kill()
        start = time.monotonic()
        proc.communicate(timeout=RELEASE_S)  # TimeoutExpired here is the hang
        released = time.monotonic() - start
        assert proc.returncode == -signal.SIGKILL and released < RELEASE_S
        assert _wait_session_gone(proc.pid) == []  # the workers and the fork server too
    finally:
        _end_session(proc)


# ------------------------------------------------------------------------------------------------ Ctrl-C
@pytest.mark.slow
@pytest.mark.parametrize(("command", "when"), [("calibrate", "server"), ("calibrate", "workers"), ("calibrate", 1.0),
                                               ("rectify", "workers"), ("synth", "workers")])
def test_ctrl_c_is_a_clean_stop_at_any_instant(command, when, data, tmp_path):
    """SIGINT to the process group, as a terminal sends it, as the fork server starts (it was loading its modules and
    printed a traceback; the run said "internal error"), as the workers start (one unpickling its task printed a
    traceback), or while they work: exit 130 and one line, nothing new on disk, no process left. ``synth`` replaces
    an earlier set (``--overwrite``), which must be left as it was."""
    args = _argv(command, data)
    if command == "synth":
        done = _lfgraph([*args[:-2], "--frames", "2", "--jobs", "1", "--quiet"], tmp_path)
        assert done.returncode == 0, done.stderr
        args = [*args, "--overwrite"]
    before = _listing(tmp_path)
    proc = _start(args, tmp_path)
    try:
        if isinstance(when, str):
            _wait_for(proc, when)
        else:
            time.sleep(when)
        assert proc.poll() is None, "the run ended before Ctrl-C"
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=RUN_S)
        text = err.decode()
        assert proc.returncode == EXIT_INTERRUPTED and "Traceback" not in text, text
        assert text.strip().splitlines()[-1] == "lfgraph: interrupted"
        assert _listing(tmp_path) == before  # nothing half-written, the earlier synthetic set untouched
        assert _wait_session_gone(proc.pid) == []
    finally:
        _end_session(proc)


# ------------------------------------------------------------------------------------------------ standard streams
def _closed(*fds: int):
    def close() -> None:
        for fd in fds:
            os.close(fd)
    return close


@pytest.mark.slow
def test_closed_standard_streams_are_not_an_error(data, tmp_path):
    """``2>&-`` and ``>&- 2>&-`` (some service managers run programs so): the work is done, exit 0 (was: exit 4
    "internal error": the progress bar wrote to a stream Python had set to None)."""
    runs = [(["calibrate", data / "cb", *BOARD, "--jobs", "2", "-o", "o.json"], (2,), "o.json"),
            (["synth", "checkerboard", "s", "--scene", "small-2x2", "--frames", "2", "--jobs", "2"], (1, 2),
             "s/truth.json")]
    for args, fds, output in runs:
        proc = _start(args, tmp_path, stdout=None, stderr=None, preexec_fn=_closed(*fds))
        try:
            assert proc.wait(RUN_S) == 0, args
        finally:
            _end_session(proc)
        assert (tmp_path / output).is_file()


@pytest.mark.slow
def test_a_reader_that_goes_away_ends_the_run_with_141_and_no_outputs(data, tmp_path):
    """``lfgraph -v calibrate ... 2>&1 | head -c 50``: exit 141 (128 + SIGPIPE, as a program a closed pipe ends),
    nothing more written, and none of the run's outputs (was: exit 1 with no message)."""
    proc = _start(["-v", *_argv("calibrate", data)], tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        head = proc.stdout.read(50)
        proc.stdout.close()  # the reader goes away
        assert len(head) == 50 and proc.wait(RUN_S) == EXIT_READER_GONE
    finally:
        _end_session(proc)
    assert _listing(tmp_path) == set()
    assert _wait_session_gone(proc.pid) == []


# ------------------------------------------------------------------------------------------------ FIFOs
@pytest.mark.slow
def test_a_fifo_in_place_of_the_detection_cache_is_never_read(data, tmp_path):
    """A FIFO as ``INPUT/.lfgraph-detections.npz`` blocked ``calibrate`` for good (nobody writes it): it is ignored
    with a warning, and neither read nor replaced."""
    capture = tmp_path / "cb"
    capture.mkdir()
    for frame in sorted((data / "cb").iterdir())[:8]:
        if frame.is_dir():
            (capture / frame.name).symlink_to(frame)
    cache = capture / ".lfgraph-detections.npz"
    os.mkfifo(cache)
    done = _lfgraph(["calibrate", capture, *BOARD, "--jobs", "1", "--quiet", "-o", tmp_path / "o.json"], tmp_path)
    assert done.returncode == 0 and "not a regular file" in done.stderr, done.stderr
    assert cache.is_fifo() and (tmp_path / "o.json").is_file()


# ------------------------------------------------------------------------------------------------ fleet
@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    root = tmp_path_factory.mktemp("fleet")
    done = _lfgraph(["synth", "scene", "knocked", "--scene", "small-2x2", "--frames", "2", "--seed", "2",
                     "--shake-rot-deg", "1.0", "--shake-trans-mm", "1", "--jobs", "2", "--quiet"], root)
    assert done.returncode == 0, done.stderr
    (root / "manifest.csv").write_text("camera,calibration,capture,max_frames\ncam,knocked/original.json,knocked,2\n")
    return root


@pytest.mark.slow
def test_a_fifo_manifest_is_refused(tmp_path):
    manifest = tmp_path / "manifest.csv"
    os.mkfifo(manifest)
    done = _lfgraph(["fleet", manifest, "-o", tmp_path / "res.csv", "--quiet"], tmp_path)
    assert done.returncode == 1 and "not a regular file" in done.stderr and manifest.is_fifo()
    assert _listing(tmp_path) == {"manifest.csv"}


@pytest.mark.slow
def test_a_fleet_run_leaves_no_temporary_and_a_failed_one_nothing_new(fleet, tmp_path, monkeypatch, capsys):
    """A successful run with a shaken camera left ``.original.v2.json.partial`` (a second link of the new version)
    and ``.res.csv.lock``; a run whose results could not be written (a full disk) left those and the version."""
    import shutil

    from lfgraph.cli import main

    work = tmp_path / "ok"
    shutil.copytree(fleet, work)
    done = _lfgraph(["fleet", "manifest.csv", "-o", "res.csv", "--jobs", "2", "--quiet"], work)
    assert done.returncode == 0, done.stderr
    assert "DRIFTED" in (work / "res.csv").read_text() and (work / "knocked" / "original.v2.json").is_file()
    assert _listing(work) - _listing(fleet) == {"res.csv", "knocked/original.v2.json"}

    work = tmp_path / "full"
    shutil.copytree(fleet, work)

    def disk_full(*_args, **_kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr("lfgraph.apps.study.write_rows", disk_full)  # lfgraph's own writer, not a library
    code = main(["fleet", str(work / "manifest.csv"), "-o", str(work / "res.csv"), "--jobs", "1", "--quiet"])
    assert code == 1 and "No space left" in capsys.readouterr().err
    assert _listing(work) == _listing(fleet)


# ------------------------------------------------------------------------------------------------ rotations
def test_rotations_printed_to_six_decimals_load_and_others_are_refused(tmp_path):
    """A 12-camera calibration whose rotations were printed to 6 decimals was refused ("views[5].R_view_from_ref: is
    not a rotation matrix") for an orthonormality error of 1.5e-6: accepted to 1e-4 and re-orthonormalised."""
    from lfgraph.core.calibration import Calibration, CalibrationFileError
    from lfgraph.datasets.rig import RigConfig, make_rig
    from lfgraph.interop.common import rotation

    printed = np.array(R_6_DECIMALS)
    assert np.max(np.abs(printed.T @ printed - np.eye(3))) > 1e-6  # the case: more than the old tolerance
    data = make_rig(RigConfig(rows=3, cols=4), np.random.default_rng(0)).to_dict()
    data["views"][5]["R_view_from_ref"] = R_6_DECIMALS
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(data))
    loaded = Calibration.load(path).ref_T_view[5, :3, :3].T  # R_view_from_ref
    assert np.max(np.abs(loaded.T @ loaded - np.eye(3))) < ORTHONORMAL_EXACT
    assert np.max(np.abs(loaded - printed)) < PRINTED_PRECISION
    imported = rotation(printed, path, "R_1")
    assert np.max(np.abs(imported.T @ imported - np.eye(3))) < ORTHONORMAL_EXACT
    for bad in (printed + 1e-3 * np.eye(3), -printed):  # not a rotation; a reflection (det -1)
        data["views"][5]["R_view_from_ref"] = bad.tolist()
        path.write_text(json.dumps(data))
        with pytest.raises(CalibrationFileError, match=r"views\[5\]\.R_view_from_ref: is not a rotation"):
            Calibration.load(path)
