#!/usr/bin/env python3
# ruff: noqa: E501  (the case tables read better one case per line)
"""A reproducible trial of bad inputs and faults over every ``lfgraph`` command and the public Python API.

Run (sequentially, ~10-15 min on 2 cores):

    .venv/bin/python benchmarks/trial_bad_inputs.py            # whole trial
    .venv/bin/python benchmarks/trial_bad_inputs.py --only 'info|api-load'   # a subset (regex on case ids)
    .venv/bin/python benchmarks/trial_bad_inputs.py --list     # list the cases

Small synthetic data (``lfgraph synth``, the ``small-2x2`` scene: 2x2 views of 320x240 px) is generated once under
``out/trial/data`` and reused (``--regen`` makes it again). Every case runs in its own folder ``out/trial/cases/ID``
holding fresh copies of the inputs it needs, in a subprocess with a hard timeout (a timeout is a HANG) and an
address-space limit (so that a runaway allocation fails instead of starving the machine). Before and after each case
the folder's files are hashed: an input changed or deleted is DATA_LOSS, as is an output (or a temporary file) left
behind by a failed run.

Classes:
    CLEAR_ERROR  non-zero exit other than 4 with a message and no Python traceback; nothing left behind (API: a
                 ValueError/TypeError/OSError or an lfgraph error type)
    CORRECT      exit 0 (or the documented code, e.g. 3 for a drift) and a result that passes the case's check
    TRACEBACK    a Python traceback (or "Exception ignored", or a crash by signal) reaches the user; API: another
                 exception type
    INTERNAL     exit code 4 ("internal error")
    HANG         the case did not end within its timeout
    DATA_LOSS    an input changed or deleted, or a partial / temporary output left behind
    SILENT_WRONG exit 0 but the result is clearly wrong (far from the synthetic truth, bad input accepted, invalid
                 JSON printed by --json, ...)

Writes ``out/trial/trial.csv`` (one row per case) and prints a summary per class and per command, then every case
that is neither CLEAR_ERROR nor CORRECT. Cases are defined in ``build_cases``; each CLI case is an argv (run with the
case folder as working directory), each API case a Python snippet run by a small harness in a fresh interpreter.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import os
import re
import resource
import shutil
import signal
import stat
import subprocess
import sys
import textwrap
import time
from collections import Counter, defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PY = ROOT / ".venv" / "bin" / "python"
LFG = ROOT / ".venv" / "bin" / "lfgraph"
OUT = ROOT / "out" / "trial"
DATA = OUT / "data"
CASES_DIR = OUT / "cases"
HARNESS = OUT / "api_harness.py"
DATA_VERSION = "3"
DEFAULT_TIMEOUT_S = 60.0
FIFO_TIMEOUT_S = 15.0
MEM_LIMIT_BYTES = 6 * 1024**3  # address space per case

CLASSES = ("CLEAR_ERROR", "CORRECT", "TRACEBACK", "INTERNAL", "HANG", "DATA_LOSS", "SILENT_WRONG")
TRACEBACK_RE = re.compile(r"Traceback \(most recent call last\)|Exception ignored in|Fatal Python error|"
                          r"Segmentation fault|core dumped|terminate called after")
TEMP_RE = re.compile(r"^\..*\.tmp|^\..*\.partial$")  # lfgraph.core.files.atomic_path's temporary files, and others
RELEASE_S = 10.0  # popen-kill: a caller that reads a killed run's pipes must get their end within this
CACHE_NAMES = {".lfgraph-detections.npz"}  # the detection cache calibrate writes into its input (documented)


# ============================================================================================ data generation
def run_quiet(argv: list[str], cwd: Path) -> None:
    r = subprocess.run([str(a) for a in argv], cwd=cwd, capture_output=True, text=True, timeout=600)
    if r.returncode != 0:
        raise SystemExit(f"data generation failed: {' '.join(map(str, argv))}\n{r.stdout}\n{r.stderr}")


def make_data(regen: bool = False) -> None:
    """Every shared input, generated once (``DATA/.stamp``)."""
    stamp = DATA / ".stamp"
    if stamp.exists() and stamp.read_text() == DATA_VERSION and not regen:
        return
    if DATA.exists():
        shutil.rmtree(DATA)
    DATA.mkdir(parents=True)
    t0 = time.time()
    print("generating the trial data under", DATA, flush=True)
    L = str(LFG)  # noqa: N806
    q = ["--jobs", "1", "--quiet"]
    run_quiet([L, "synth", "checkerboard", "cb", "--scene", "small-2x2", *q], DATA)
    run_quiet([L, "synth", "checkerboard", "cb_mosaic", "--scene", "small-2x2", "--layout", "mosaic", *q], DATA)
    run_quiet([L, "synth", "checkerboard", "cb40", "--scene", "small-2x2", "--frames", "40", *q], DATA)
    run_quiet([L, "synth", "checkerboard", "cb12", "--scene", "small-2x2", "--grid", "1x2", "--frames", "6", *q], DATA)
    run_quiet([L, "synth", "scene", "sc", "--scene", "small-2x2", "--frames", "2", "--shake-rot-deg", "0.5",
               "--shake-trans-mm", "2", "--shake-axis", "any", *q], DATA)
    run_quiet([L, "synth", "scene", "sc_still", "--scene", "small-2x2", "--frames", "2", *q], DATA)
    run_quiet([L, "synth", "scene", "sc6", "--scene", "small-2x2", "--frames", "6", *q], DATA)
    run_quiet([L, "synth", "scene", "sc_big", "--scene", "small-2x2", "--frames", "12", "--shake-rot-deg", "0.5",
               "--shake-trans-mm", "2", "--shake-axis", "any", *q], DATA)
    run_quiet([L, "synth", "scene", "other_seed", "--scene", "small-2x2", "--frames", "2", "--seed", "7", *q], DATA)
    run_quiet([L, "synth", "scene", "other_size", "--scene", "small-2x2", "--frames", "1", "--image-size", "400x300",
               *q], DATA)
    run_quiet([L, "calibrate", "cb", "--grid", "2x2", "--board", "7x5", "--square-mm", "15", "-o", "cal.json", *q],
              DATA)
    run_quiet([L, "rectify", "cal.json", "cb", "-o", "rect", *q], DATA)
    shutil.copy(DATA / "rect" / "calibration.json", DATA / "cal_rect.json")
    shutil.rmtree(DATA / "rect")
    for fmt, name in (("opencv-yaml", "cal.yaml"), ("kalibr", "camchain.yaml"), ("colmap", "colmap"),
                      ("json", "cal_export.json")):
        run_quiet([L, "export", "cal.json", "--to", fmt, "-o", name], DATA)
    # detections from another tool: lfgraph's own npz and OpenCV's multi-view JSON, from the same boards
    code = textwrap.dedent("""
        import json, numpy as np, lfgraph as lf
        from lfgraph.io.points import write_points_npz
        cap = lf.open_capture("cb", (2, 2))
        obs, _ = lf.detect_capture(cap, lf.BoardSpec.parse("7x5", 15), jobs=1, progress=False)
        write_points_npz("points.npz", obs)
        import pathlib
        mv = pathlib.Path("mv"); mv.mkdir()
        np.save("obj.npy", obs.board.object_points())
        for v in range(obs.corners_px.shape[0]):
            nodes = {f"frame_{f}": obs.corners_px[v, f].ravel().tolist()
                     for f in range(obs.corners_px.shape[1]) if obs.valid[v, f].all()}
            (mv / f"cam_{v}.json").write_text(json.dumps(nodes))
    """)
    run_quiet([PY, "-c", code], DATA)
    # other layouts of the same boards: hci (input_CamNNN.png) and video (one mp4 per view)
    code = textwrap.dedent("""
        import cv2, pathlib, shutil
        src = pathlib.Path("cb"); hci = pathlib.Path("cb_hci"); vid = pathlib.Path("cb_video")
        vid.mkdir()
        frames = sorted(p for p in src.iterdir() if p.is_dir())
        names = ["r00_c00", "r00_c01", "r01_c00", "r01_c01"]
        for f in frames:
            (hci / f.name).mkdir(parents=True)
            for v, n in enumerate(names):
                shutil.copy(f / f"{n}.png", hci / f.name / f"input_Cam{v:03d}.png")
        for v, n in enumerate(names):
            w = cv2.VideoWriter(str(vid / f"cam_{v}.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10, (320, 240))
            assert w.isOpened()
            for f in frames:
                w.write(cv2.cvtColor(cv2.imread(str(f / f"{n}.png"), cv2.IMREAD_GRAYSCALE), cv2.COLOR_GRAY2BGR))
            w.release()
    """)
    run_quiet([PY, "-c", code], DATA)
    (DATA / "calib.txt").write_text("cam0=[300 0 160; 0 300 120; 0 0 1]\ncam1=[300 0 162; 0 300 120; 0 0 1]\n"
                                    "doffs=2\nbaseline=10.0\nwidth=320\nheight=240\nndisp=64\n")
    (DATA / "parameters.cfg").write_text(
        "[intrinsics]\nfocal_length_mm = 100\nsensor_size_mm = 35\nimage_resolution_x_px = 320\n"
        "image_resolution_y_px = 240\n\n[extrinsics]\nnum_cams_x = 2\nnum_cams_y = 2\nbaseline_mm = 10\n")
    (DATA / "manifest.csv").write_text("camera,calibration,capture\ncam1,sc/original.json,sc\n")
    stamp.write_text(DATA_VERSION)
    print(f"data generated in {time.time() - t0:.1f} s", flush=True)


# ============================================================================================ file snapshots
def snapshot(root: Path) -> dict[str, tuple]:
    """Relative path -> (kind, content hash or link target) of everything under ``root`` (links not followed)."""
    out: dict[str, tuple] = {}
    for dirpath, dirnames, filenames in os.walk(root, followlinks=False):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            rel = str(p.relative_to(root))
            try:
                st = os.lstat(p)
            except OSError:
                continue
            if stat.S_ISLNK(st.st_mode):
                out[rel] = ("link", os.readlink(p))
            elif stat.S_ISDIR(st.st_mode):
                out[rel] = ("dir",)
            elif stat.S_ISREG(st.st_mode):
                h = hashlib.sha256()
                with open(p, "rb") as fh:
                    for chunk in iter(lambda: fh.read(1 << 20), b""):
                        h.update(chunk)
                out[rel] = ("file", h.hexdigest())
            else:
                out[rel] = ("special", stat.S_IFMT(st.st_mode))
    return out


def diff_snapshots(before: dict, after: dict) -> tuple[list[str], list[str]]:
    """(changed or deleted entries, new entries)."""
    changed = [k for k, v in before.items() if after.get(k) != v and v[0] != "dir"]
    changed += [k for k, v in before.items() if v[0] == "dir" and k not in after]
    new = [k for k in after if k not in before]
    return sorted(changed), sorted(new)


# ============================================================================================ cases
@dataclass
class Case:
    id: str
    command: str
    desc: str
    kind: str = "cli"  # cli | api | sigint | sigkill | popen-kill | pipe | shell
    argv: list[str] = field(default_factory=list)
    code: str = ""  # api snippet, or shell command for kind=shell
    setup: Callable[[Path], None] | None = None
    expect: str = "error"  # error | ok | either
    check: Callable[[Case, Path, Result], tuple[bool, str]] | None = None
    ok_codes: tuple[int, ...] = (0,)
    allow_new: tuple[str, ...] = ()  # regexes of new paths allowed even after an error
    mutable: tuple[str, ...] = ()  # regexes of existing paths the case may change
    timeout: float = DEFAULT_TIMEOUT_S
    delay: float = 1.0  # sigint/sigkill/popen-kill: seconds before the signal; pipe: bytes to read
    allowed_exc: tuple[str, ...] = ()  # api: extra exception type names that are the right answer
    teardown: Callable[[Path], None] | None = None  # after the case (e.g. unmount a file system the setup mounted)


@dataclass
class Result:
    rc: int | None = None
    stdout: str = ""
    stderr: str = ""
    seconds: float = 0.0
    timed_out: bool = False
    api: dict | None = None
    notes: list[str] = field(default_factory=list)


def preexec() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (MEM_LIMIT_BYTES, MEM_LIMIT_BYTES))
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))


def _kill_group(pgid: int) -> None:
    try:
        os.killpg(pgid, signal.SIGKILL)
    except ProcessLookupError:
        pass


def _group_alive(pgid: int) -> bool:
    """Whether a process of the group still runs; a zombie (dead, waiting for init to reap it, which takes up to ~2 s
    on some machines) holds no file or pipe and does not count."""
    if Path("/proc/self/stat").exists():
        for entry in Path("/proc").iterdir():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split() if entry.name.isdigit() else None
            except (OSError, IndexError):
                continue
            if fields and int(fields[2]) == pgid and fields[0] not in ("Z", "X"):
                return True
        return False
    try:
        os.killpg(pgid, 0)
        return True
    except ProcessLookupError:
        return False
    except PermissionError:
        return True


def _popen_kill(argv: list[str], d: Path, env: dict, case: Case, res: Result) -> subprocess.Popen:
    """The bounded run of Python's documentation: ``communicate(timeout)``, on TimeoutExpired ``kill()``, then
    ``communicate()`` (bounded here by RELEASE_S: the pipes must reach their end once the run is killed)."""
    p = subprocess.Popen(argv, cwd=d, stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL,
                         start_new_session=True, preexec_fn=preexec, env=env)
    try:
        out, err = p.communicate(timeout=case.delay)
        res.notes.append("finished before the kill")
    except subprocess.TimeoutExpired:
        p.kill()
        t0 = time.time()
        try:
            out, err = p.communicate(timeout=RELEASE_S)
            res.notes.append(f"caller released {time.time() - t0:.2f} s after the kill")
        except subprocess.TimeoutExpired:
            res.timed_out = True
            res.notes.append(f"caller not released {RELEASE_S:.0f} s after the kill (the run's pipes stay open)")
            _kill_group(p.pid)
            out, err = p.communicate()
    (d.parent / f"{case.id}.stdout").write_bytes(out)
    (d.parent / f"{case.id}.stderr").write_bytes(err)
    return p


def _reap_group(pgid: int, res: Result) -> None:
    """Give a finished run's process group 3 s to end; what is left outlived it: noted and killed."""
    deadline = time.time() + 3.0
    while _group_alive(pgid) and time.time() < deadline:
        time.sleep(0.1)
    if _group_alive(pgid):
        res.notes.append("processes of the run outlived it (killed)")
        _kill_group(pgid)


def _cmd(case: Case) -> list[str]:
    return [str(LFG), *case.argv]


def run_case(case: Case, d: Path) -> Result:
    res = Result()
    out_f, err_f = d.parent / f"{case.id}.stdout", d.parent / f"{case.id}.stderr"
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "COLUMNS": "200", "TQDM_DISABLE": "0"}
    if case.kind == "api":
        (d.parent / f"{case.id}.snippet.py").write_text(case.code)
        argv = [str(PY), str(HARNESS), str(d), str(d.parent / f"{case.id}.snippet.py"),
                str(d.parent / f"{case.id}.result.json")]
    elif case.kind == "shell":
        argv = ["bash", "-c", case.code.replace("LFG", str(LFG))]
    else:
        argv = _cmd(case)
    t0 = time.time()
    if case.kind == "popen-kill":
        p = _popen_kill(argv, d, env, case, res)
        res.rc, res.seconds = p.returncode, time.time() - t0
        _reap_group(p.pid, res)
        res.stdout = out_f.read_bytes().decode("utf-8", "replace")
        res.stderr = err_f.read_bytes().decode("utf-8", "replace")
        return res
    with open(out_f, "wb") as fo, open(err_f, "wb") as fe:
        if case.kind == "pipe":
            p = subprocess.Popen(argv, cwd=d, stdout=subprocess.PIPE, stderr=fe, stdin=subprocess.DEVNULL,
                                 start_new_session=True, preexec_fn=preexec, env=env)
            n = int(case.delay)
            got = b""
            try:
                if n > 0:
                    while len(got) < n:
                        chunk = p.stdout.read(n - len(got))
                        if not chunk:
                            break
                        got += chunk
            finally:
                p.stdout.close()  # the reader goes away, as `| head -c N` does
            fo.write(got)
        else:
            p = subprocess.Popen(argv, cwd=d, stdout=fo, stderr=fe, stdin=subprocess.DEVNULL,
                                 start_new_session=True, preexec_fn=preexec, env=env)
        if case.kind in ("sigint", "sigkill"):
            time.sleep(case.delay)
            if p.poll() is None:
                if case.kind == "sigint":
                    os.killpg(p.pid, signal.SIGINT)  # Ctrl-C reaches the whole foreground group
                else:
                    os.kill(p.pid, signal.SIGKILL)  # only the parent: its workers must die with it
            else:
                res.notes.append("finished before the signal")
        try:
            p.wait(timeout=case.timeout)
        except subprocess.TimeoutExpired:
            res.timed_out = True
            _kill_group(p.pid)
            p.wait()
        res.rc = p.returncode
        res.seconds = time.time() - t0
        if case.kind in ("sigint", "sigkill", "cli", "pipe", "shell", "api"):
            _reap_group(p.pid, res)
    res.stdout = out_f.read_bytes().decode("utf-8", "replace")
    res.stderr = err_f.read_bytes().decode("utf-8", "replace")
    if case.kind == "api":
        rj = d.parent / f"{case.id}.result.json"
        if rj.exists():
            try:
                res.api = json.loads(rj.read_text())
            except ValueError:
                res.api = None
    return res


HARNESS_CODE = r'''
import json, os, sys, traceback
from pathlib import Path
case_dir, snippet, result = sys.argv[1], sys.argv[2], sys.argv[3]
os.chdir(case_dir)
out = {"status": "started"}
def dump():
    with open(result, "w") as fh:
        json.dump(out, fh)
dump()
try:
    import numpy as np
    import lfgraph as lf
    ns = {"lf": lf, "np": np, "Path": Path, "__name__": "__trial__"}
    exec(compile(open(snippet).read(), "<case>", "exec"), ns)
    out = {"status": "ok", "verdict": ns.get("verdict")}
except BaseException as exc:  # noqa: BLE001
    frames = traceback.extract_tb(exc.__traceback__)
    last = frames[-1] if frames else None
    allowed = isinstance(exc, (ValueError, TypeError, OSError)) or type(exc).__module__.split(".")[0] == "lfgraph"
    out = {"status": "exc", "type": type(exc).__name__, "module": type(exc).__module__, "allowed": allowed,
           "msg": " ".join(str(exc).split())[:300],
           "where": f"{last.filename}:{last.lineno} in {last.name}" if last else "",
           "lfgraph_where": next((f"{f.filename.split('/lfgraph/')[-1]}:{f.lineno} in {f.name}" for f in reversed(frames)
                                  if "/lfgraph/" in f.filename), "")}
    traceback.print_exc()
dump()
'''


def first_line(text: str) -> str:
    for line in text.splitlines():
        line = line.strip().replace("\r", "")
        if line and not re.match(r"^[\w ]*:?\s*\d+%\|", line):
            return line[:300]
    return ""


def message_line(text: str) -> str:
    """The line that says what went wrong: 'lfgraph: ...', 'usage error', else the last line."""
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    for ln in lines:
        if ln.startswith("lfgraph: error") or ln.startswith("lfgraph: internal") or ln.startswith("lfgraph: interr"):
            return ln[:300]
    for ln in lines:
        if "error:" in ln:
            return ln[:300]
    return lines[-1][:300] if lines else ""


def _temporary(path: str) -> bool:
    """A temporary file, or anything inside a temporary folder (``.NAME.PID.XXXX.tmp/...``)."""
    return any(TEMP_RE.match(part) for part in Path(path).parts)


def classify(case: Case, d: Path, res: Result, changed: list[str], new: list[str]) -> tuple[str, str]:
    notes = list(res.notes)
    if res.timed_out:
        return "HANG", "; ".join([f"no end within {case.timeout:.0f} s", *notes])
    if any("outlived" in n for n in notes):
        return "HANG", "; ".join(notes)
    changed = [c for c in changed if not any(re.search(m, c) for m in case.mutable)
               and Path(c).name not in CACHE_NAMES]
    if changed:
        return "DATA_LOSS", "; ".join([f"input changed/deleted: {', '.join(changed[:4])}", *notes])
    temps = [n for n in new if _temporary(n) or n.endswith(".lock")]  # a lock left after the run is a leftover too
    unexpected_new = [n for n in new if Path(n).name not in CACHE_NAMES
                      and not any(re.search(m, n) for m in case.allow_new)]
    if case.kind == "api":
        api = res.api or {}
        if api.get("status") == "exc":
            where = api.get("lfgraph_where") or api.get("where", "")
            notes.append(f"{api['type']}: {api['msg'][:160]} [{where}]")
            if api["type"] == "AssertionError" and api.get("where", "").startswith("<case>"):
                return "SILENT_WRONG", "; ".join(["the call returned a wrong result (the snippet's check failed)",
                                                  *notes])
            if api["type"] in case.allowed_exc:
                return ("DATA_LOSS", "; ".join(["left " + ", ".join(unexpected_new[:4]), *notes])) \
                    if unexpected_new else ("CLEAR_ERROR", "; ".join(notes))
            if not api.get("allowed"):
                return "TRACEBACK", "; ".join(notes)
            if unexpected_new:
                return "DATA_LOSS", "; ".join(["left " + ", ".join(unexpected_new[:4]), *notes])
            if case.expect == "ok":
                notes.append("refused an input that should work")
            if not ("/lfgraph/" in api.get("where", "") or api.get("where", "").startswith("<case>")):
                notes.append(f"raised outside lfgraph: {api.get('where', '')}")
            return "CLEAR_ERROR", "; ".join(notes)
        if api.get("status") != "ok":
            return "TRACEBACK", "; ".join([f"interpreter died (exit {res.rc}) without a result", *notes])
        if temps:
            return "DATA_LOSS", "; ".join(["temporary file left: " + ", ".join(temps[:3]), *notes])
        verdict = api.get("verdict")
        if verdict:
            cls, note = verdict
            return cls, "; ".join([note, *notes])
        if case.expect == "error":
            return "SILENT_WRONG", "; ".join(["returned without an error", *notes])
        return "CORRECT", "; ".join(notes)
    # command line
    crashed = res.rc is not None and res.rc < 0 and case.kind not in ("sigkill", "popen-kill")
    if TRACEBACK_RE.search(res.stderr) or crashed:
        if crashed:
            notes.append(f"killed by signal {-res.rc}")
        return "TRACEBACK", "; ".join(notes)
    if res.rc == 4:
        if unexpected_new:
            notes.append("and left " + ", ".join(unexpected_new[:3]))
        return "INTERNAL", "; ".join(notes)
    if case.kind in ("sigkill", "popen-kill"):
        if unexpected_new and not all(_temporary(n) for n in unexpected_new):
            # a run that finished its work before the kill landed leaves its whole output: not a loss, if it is whole
            if case.check is not None and case.check(case, d, res)[0]:
                return "CORRECT", "; ".join(["finished before the kill: " + case.check(case, d, res)[1], *notes])
            return "DATA_LOSS", "; ".join(["left " + ", ".join(unexpected_new[:4]), *notes])
        if temps:
            notes.append("temporary files left (unavoidable after SIGKILL)")
        return "CLEAR_ERROR", "; ".join(notes)
    if res.rc not in case.ok_codes:
        if case.check is not None and case.kind in ("pipe", "shell"):
            ok, note = case.check(case, d, res)
            notes.append(note)
            if not ok:
                return "DATA_LOSS", "; ".join(notes)
            unexpected_new = []
        if unexpected_new:
            return "DATA_LOSS", "; ".join(["failed run left " + ", ".join(unexpected_new[:4]), *notes])
        if not res.stderr.strip():
            notes.append("no message at all")
        if case.expect == "ok":
            notes.append("refused an input that should work")
        return "CLEAR_ERROR", "; ".join(notes)
    if temps:
        return "DATA_LOSS", "; ".join(["temporary file left: " + ", ".join(temps[:3]), *notes])
    if case.check is not None:
        try:
            ok, note = case.check(case, d, res)
        except Exception as exc:  # noqa: BLE001  a check that cannot even read the output: the output is wrong
            ok, note = False, f"check failed: {type(exc).__name__}: {' '.join(str(exc).split())[:200]}"
        notes.insert(0, note)
        return ("CORRECT" if ok else "SILENT_WRONG"), "; ".join(notes)
    if case.expect == "error":
        return "SILENT_WRONG", "; ".join(["exit 0 on bad input", *notes])
    return "CORRECT", "; ".join(notes)


# ============================================================================================ setup helpers
def _copy(src: Path, dst: Path) -> None:
    if src.is_dir():
        shutil.copytree(src, dst, symlinks=True)
    else:
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(src, dst)


def use(*names: str) -> Callable[[Path], None]:
    """Copy DATA/name (file or folder) into the case folder; ``a=b`` copies DATA/b as a."""
    def f(d: Path) -> None:
        for n in names:
            dst, _, src = n.partition("=")
            _copy(DATA / (src or dst), d / dst)
    return f


def chain(*fns: Callable[[Path], None] | None) -> Callable[[Path], None]:
    def f(d: Path) -> None:
        for fn in fns:
            if fn is not None:
                fn(d)
    return f


def put(name: str, content: str | bytes) -> Callable[[Path], None]:
    def f(d: Path) -> None:
        p = d / name
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(content if isinstance(content, bytes) else content.encode())
    return f


def mkdirs(*names: str) -> Callable[[Path], None]:
    def f(d: Path) -> None:
        for n in names:
            (d / n).mkdir(parents=True, exist_ok=True)
    return f


def fifo(name: str) -> Callable[[Path], None]:
    def f(d: Path) -> None:
        p = d / name
        p.parent.mkdir(parents=True, exist_ok=True)
        if p.exists() or p.is_symlink():
            p.unlink()
        os.mkfifo(p)
    return f


def device(name: str, major: int = 1, minor: int = 3) -> Callable[[Path], None]:
    """A character device node of our own (1,3 = null, 1,7 = full) standing for /dev/null: output cases must never
    touch the real /dev/null (a command that replaces its output atomically would replace the system's device)."""
    def f(d: Path) -> None:
        p = d / name
        p.parent.mkdir(parents=True, exist_ok=True)
        os.mknod(p, 0o666 | stat.S_IFCHR, os.makedev(major, minor))
    return f


def symlink(name: str, target: str) -> Callable[[Path], None]:
    def f(d: Path) -> None:
        p = d / name
        if p.exists() or p.is_symlink():
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            else:
                p.unlink()
        p.parent.mkdir(parents=True, exist_ok=True)
        os.symlink(target, p)
    return f


def remove(*names: str) -> Callable[[Path], None]:
    def f(d: Path) -> None:
        for n in names:
            p = d / n
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            elif p.exists() or p.is_symlink():
                p.unlink()
    return f


FULL_FS_KIB = 200  # the size of the tmpfs a "full disk" case mounts (root only, as the device-node cases)


def full_fs(name: str, free_kib: int, files: dict[str, str]) -> tuple[Callable[[Path], None], Callable[[Path], None]]:
    """(setup, teardown): a tmpfs of FULL_FS_KIB KiB mounted at ``name`` in the case folder, holding ``files``
    (path in the tmpfs -> source under the case folder, or ``"text:..."``), then filled up to ``free_kib`` KiB free
    (``fill``); the teardown unmounts it. Writes beyond the free space fail with ENOSPC, as on a full disk."""
    def setup(d: Path) -> None:
        root = d / name
        root.mkdir()
        subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={FULL_FS_KIB}k", "tmpfs", str(root)], check=True,
                       timeout=30)
        for dst, src in files.items():
            (root / dst).parent.mkdir(parents=True, exist_ok=True)
            if src.startswith("text:"):
                (root / dst).write_text(src[len("text:"):].replace("CASE", str(d)))
            else:
                shutil.copy(d / src, root / dst)
        st = os.statvfs(root)
        (root / "fill").write_bytes(b"\0" * max(0, st.f_bavail * st.f_frsize - free_kib * 1024))

    def teardown(d: Path) -> None:
        subprocess.run(["umount", str(d / name)], check=False, timeout=30)
    return setup, teardown


def still_special(name: str):
    """Check: ``name`` is still a FIFO or device (never replaced by a regular file)."""
    def check(case: Case, d: Path, res: Result) -> tuple[bool, str]:
        mode = os.lstat(d / name).st_mode
        ok = stat.S_ISFIFO(mode) or stat.S_ISCHR(mode)
        return ok, f"{name} {'left as it was' if ok else 'was replaced by a regular file'}"
    return check


# a rotation as HALCON (and many tools) print it, to 6 decimals: R^T R is I only to 1.5e-6
R_6_DECIMALS = [[0.844693, 0.189133, -0.500721], [-0.073738, 0.967689, 0.241124], [0.530147, -0.166754, 0.831346]]


def twelve_views_printed(name: str) -> Callable[[Path], None]:
    """A 3x4 calibration whose views[5] rotation is printed to 6 decimals (the case as it was reported)."""
    def f(d: Path) -> None:
        from lfgraph.datasets.rig import RigConfig, make_rig

        data = make_rig(RigConfig(rows=3, cols=4), np.random.default_rng(0)).to_dict()
        data["views"][5]["R_view_from_ref"] = R_6_DECIMALS
        (d / name).write_text(json.dumps(data))
    return f


def base_cal() -> dict:
    return json.loads((DATA / "cal.json").read_text())


def json_variant(name: str, mutate: Callable[[dict], object], src: str = "cal.json") -> Callable[[Path], None]:
    """Write DATA/src with ``mutate(d)`` applied (NaN and infinities are written as JSON's NaN tokens)."""
    def f(d: Path) -> None:
        data = json.loads((DATA / src).read_text())
        r = mutate(data)
        if isinstance(r, Replace):
            data = r.value
        (d / name).write_text(json.dumps(data, indent=1, allow_nan=True))
    return f


@dataclass
class Replace:
    """What a mutation returns to replace the whole document."""

    value: object


def raw_variant(name: str, mutate: Callable[[bytes], bytes], src: str = "cal.json") -> Callable[[Path], None]:
    def f(d: Path) -> None:
        (d / name).write_bytes(mutate((DATA / src).read_bytes()))
    return f


def setp(d: object, path: tuple, value: object) -> None:
    for k in path[:-1]:
        d = d[k]  # type: ignore[index]
    d[path[-1]] = value  # type: ignore[index]


def delp(d: object, path: tuple) -> None:
    for k in path[:-1]:
        d = d[k]  # type: ignore[index]
    del d[path[-1]]  # type: ignore[attr-defined]


def S(*path_value) -> Callable[[dict], None]:  # noqa: N802
    """Mutation: set the nested field ``path`` (all but the last argument) to the last argument."""
    *path, value = path_value
    return lambda d: setp(d, tuple(path), value)


def D(*path) -> Callable[[dict], None]:  # noqa: N802
    return lambda d: delp(d, tuple(path))


VIEW_NAMES = ("r00_c00", "r00_c01", "r01_c00", "r01_c01")


def frame_dirs(root: Path) -> list[Path]:
    return sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))


def images(cap: str, fn: Callable[[np.ndarray, int, int], np.ndarray | None], frames: object = None,
           views: object = None, ext: str | None = None, imread_flag: int = 0) -> Callable[[Path], None]:
    """Rewrite images of capture folder ``cap`` (folders layout): fn(img, frame, view) -> new image (None keeps)."""
    import cv2

    def f(d: Path) -> None:
        for fi, fd in enumerate(frame_dirs(d / cap)):
            if frames is not None and fi not in frames:
                continue
            for vi, vn in enumerate(VIEW_NAMES):
                if views is not None and vi not in views:
                    continue
                p = fd / f"{vn}.png"
                img = cv2.imread(str(p), imread_flag)
                new = fn(img, fi, vi)
                if new is None:
                    continue
                target = p if ext is None else p.with_suffix(ext)
                if ext is not None:
                    p.unlink()
                assert cv2.imwrite(str(target), new), target
    return f


def file_op(cap: str, fn: Callable[[Path], None], frames: object = (0,), views: object = (0,)) -> Callable:
    """Apply fn(path) to view images of ``cap`` (folders layout)."""
    def f(d: Path) -> None:
        for fi, fd in enumerate(frame_dirs(d / cap)):
            if frames is not None and fi not in frames:
                continue
            for vi, vn in enumerate(VIEW_NAMES):
                if views is None or vi in views:
                    fn(fd / f"{vn}.png")
    return f


def _truncate(p: Path) -> None:
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])


def _zero(p: Path) -> None:
    p.write_bytes(b"")


def _garbage(p: Path) -> None:
    p.write_bytes(np.random.default_rng(1).integers(0, 256, 5000, dtype=np.uint8).tobytes())


def _text(p: Path) -> None:
    p.write_text("this is not an image\n")


def _to_dir(p: Path) -> None:
    p.unlink()
    p.mkdir()


def _to_fifo(p: Path) -> None:
    p.unlink()
    os.mkfifo(p)


def _dangling(p: Path) -> None:
    p.unlink()
    os.symlink("/nonexistent/image.png", p)


def _jpeg_in_png(p: Path) -> None:
    import cv2

    img = cv2.imread(str(p), 0)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 98])
    p.write_bytes(buf.tobytes())


# ============================================================================================ checks
def _lf():
    import lfgraph as lf

    return lf


def errors_vs(out: Path, truth: Path) -> dict:
    lf = _lf()
    return lf.evaluate(lf.Calibration.load(out), lf.Calibration.load(truth)).summary()


def calib_close(out: str, truth: str, fx_px: float = 3.0, pos_mm: float = 1.0, rot_deg: float = 0.2):
    """Check: the written calibration is near the synthetic truth (generous bounds; a good run is 10-50x inside)."""
    def check(case: Case, d: Path, res: Result) -> tuple[bool, str]:
        p = d / out
        if not p.exists():
            return False, f"exit 0 but {out} was not written"
        s = errors_vs(p, d / truth)
        note = (f"vs truth: fx {s['rms_fx_px']:.3g} px, position {s['rms_position_mm']:.3g} mm, "
                f"rotation {s['rms_rotation_deg']:.3g} deg")
        ok = s["rms_fx_px"] < fx_px and s["rms_position_mm"] < pos_mm and s["rms_rotation_deg"] < rot_deg
        return ok, note
    return check


def not_worse(out: str, before: str, truth: str, slack_deg: float = 0.02, slack_mm: float = 0.5):
    """Check for refine: the written calibration is not further from the truth than its input (rotation, position)."""
    def check(case: Case, d: Path, res: Result) -> tuple[bool, str]:
        p = d / out
        if not p.exists():
            return False, f"exit 0 but {out} was not written"
        a, b = errors_vs(d / before, d / truth), errors_vs(p, d / truth)
        note = (f"rotation {a['rms_rotation_deg']:.3g} -> {b['rms_rotation_deg']:.3g} deg, position "
                f"{a['rms_position_mm']:.3g} -> {b['rms_position_mm']:.3g} mm, fx {a['rms_fx_px']:.3g} -> "
                f"{b['rms_fx_px']:.3g} px")
        ok = (b["rms_rotation_deg"] <= a["rms_rotation_deg"] + slack_deg
              and b["rms_position_mm"] <= a["rms_position_mm"] + slack_mm
              and b["rms_fx_px"] <= a["rms_fx_px"] + 1.0 and np.isfinite(list(b.values())).all())
        return ok, note
    return check


def exists_check(*names: str, min_files: int = 1):
    def check(case: Case, d: Path, res: Result) -> tuple[bool, str]:
        for n in names:
            p = d / n
            if not p.exists():
                return False, f"{n} missing"
            if p.is_dir() and sum(1 for _ in p.rglob("*") if _.is_file()) < min_files:
                return False, f"{n} holds fewer than {min_files} files"
            if p.is_file() and p.stat().st_size == 0:
                return False, f"{n} is empty"
        return True, "outputs present"
    return check


def loads_check(name: str):
    def check(case: Case, d: Path, res: Result) -> tuple[bool, str]:
        lf = _lf()
        c = lf.Calibration.load(d / name)
        return True, f"{name} loads ({c.num_views} views)"
    return check


def strict_json_stdout(extra: Callable[[object], tuple[bool, str]] | None = None):
    """Check: standard output is strict JSON (no NaN/Infinity tokens)."""
    def check(case: Case, d: Path, res: Result) -> tuple[bool, str]:
        def bad(name: str) -> float:
            raise ValueError(f"non-standard JSON token {name}")
        try:
            data = json.loads(res.stdout, parse_constant=bad)
        except ValueError as exc:
            return False, f"--json output is not strict JSON ({' '.join(str(exc).split())[:100]})"
        if extra is not None:
            return extra(data)
        return True, "strict JSON"
    return check


def rc_is(code: int, why: str):
    def check(case: Case, d: Path, res: Result) -> tuple[bool, str]:
        return res.rc == code, f"exit {res.rc} ({why}: expected {code})"
    return check


def not_ok_verdict(why: str):
    """``check --json``: DRIFT (exit 3) or UNCERTAIN (exit 0, "no view could be confirmed OK"), never OK."""
    def check(case: Case, d: Path, res: Result) -> tuple[bool, str]:
        try:
            verdict = json.loads(res.stdout).get("verdict")
        except (ValueError, AttributeError):
            verdict = None
        return (res.rc == 3 or verdict == "UNCERTAIN"), f"exit {res.rc}, verdict {verdict} ({why}: expected not OK)"
    return check


def all_of(*checks):
    def check(case: Case, d: Path, res: Result) -> tuple[bool, str]:
        notes = []
        for c in checks:
            ok, note = c(case, d, res)
            notes.append(note)
            if not ok:
                return False, "; ".join(notes)
        return True, "; ".join(notes)
    return check


def rectified_check(out: str, frames: int):
    def check(case: Case, d: Path, res: Result) -> tuple[bool, str]:
        lf = _lf()
        p = d / out
        c = lf.Calibration.load(p / "calibration.json")
        n = len([q for q in p.iterdir() if q.is_dir()])
        pngs = len(list(p.rglob("*.png")))
        ok = c.rectification is not None and n == frames and pngs == frames * c.num_views
        return ok, f"{n} frame folders, {pngs} images, rectification {'stored' if c.rectification else 'missing'}"
    return check


def roundtrip_check(out: str, fmt: str, src: str = "cal.json", grid: str = "2x2"):
    """Check for export: import the written file back and compare with the source calibration."""
    def check(case: Case, d: Path, res: Result) -> tuple[bool, str]:
        lf = _lf()
        r = subprocess.run([str(LFG), "import", out, "--from", fmt, "--grid", grid, "-o", "_back.json"], cwd=d,
                           capture_output=True, text=True, timeout=60)
        if r.returncode != 0:
            return False, f"the export does not import back: {message_line(r.stderr)}"
        a, b = lf.Calibration.load(d / src), lf.Calibration.load(d / "_back.json")
        (d / "_back.json").unlink()
        ka = np.array([i.K for i in a.intrinsics])
        kb = np.array([i.K for i in b.intrinsics])
        dk = float(np.max(np.abs(ka - kb) / np.maximum(1.0, np.abs(ka))))
        # relative to the rig's largest entry (Kalibr's camera-to-camera chain turns a 1e300 m translation into
        # ~1e284 m of round-off in the next view)
        scale = max(1.0, float(np.max(np.abs(a.ref_T_view))))
        dt = float(np.max(np.abs(a.ref_T_view - b.ref_T_view) / scale))
        ok = dk < 1e-6 and dt < 1e-6
        return ok, f"round trip: max relative K difference {dk:.2g}, relative pose difference {dt:.2g}"
    return check


def depth_check(res_json: dict) -> tuple[bool, str]:
    """Against lfgraph.judge.depth's documented formula: half the spread of the depths at disparity d - E and d + E,
    d = f b / z, infinite (null in JSON) where E >= d."""
    f, b, e = res_json["focal_px"], res_json["baseline_m"], res_json["error_px"]
    worst = 0.0
    for z, dz in zip(res_json["depth_m"], res_json["depth_error_m"], strict=True):
        with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
            fb = np.float64(f) * b
            d = fb / z
            want = float((fb / (d - e) - fb / (d + e)) / 2.0) if d > e else float("inf")
        if not np.isfinite(want):
            if dz is None or not np.isfinite(dz):
                continue
            return False, f"depth error at {z} m is {dz}; expected infinite (null)"
        if dz is None or not np.isfinite(dz):
            return False, f"depth error at {z} m is {dz}; expected {want:.3g}"
        worst = max(worst, abs(dz - want) / max(abs(want), 1e-300))
    return worst < 1e-6, f"depth errors within {worst:.2g} (relative) of the documented formula"


def csv_rows_check(name: str, min_rows: int = 1, column: str | None = None, value: str | None = None):
    def check(case: Case, d: Path, res: Result) -> tuple[bool, str]:
        p = d / name
        if not p.exists():
            return False, f"{name} missing"
        with open(p, newline="") as fh:
            rows = list(csv.DictReader(fh))
        if len(rows) < min_rows:
            return False, f"{name} has {len(rows)} rows"
        if column is not None and not any(r.get(column) == value for r in rows):
            return False, f"{name}: no row with {column}={value} ({[r.get(column) for r in rows]})"
        return True, f"{name}: {len(rows)} rows" + (f", {column}={value}" if column else "")
    return check


# ============================================================================================ the cases
NAN, INF = float("nan"), float("inf")
BOARD = ["--board", "7x5", "--square-mm", "15"]
CALARGS = ["--grid", "2x2", *BOARD]
Q = ["--jobs", "1", "--quiet"]


def _cal_variants() -> list[tuple[str, str, Callable[[Path], None], str]]:
    """(id suffix, description, setup writing c.json, expectation) for calibration.json files."""
    v: list[tuple[str, str, Callable[[Path], None], str]] = []

    def jv(key: str, desc: str, mut: Callable[[dict], object], expect: str = "error", src: str = "cal.json"):
        v.append((key, desc, json_variant("c.json", mut, src), expect))

    def rv(key: str, desc: str, mut: Callable[[bytes], bytes], expect: str = "error"):
        v.append((key, desc, raw_variant("c.json", mut), expect))

    v.append(("missing", "calibration file does not exist", lambda d: None, "error"))
    rv("empty", "empty file (0 bytes)", lambda b: b"")
    rv("truncated", "truncated JSON (first half)", lambda b: b[: len(b) // 2])
    rv("garbage", "random binary garbage", lambda b: np.random.default_rng(0).integers(0, 256, 4096, np.uint8).tobytes())
    rv("utf16", "valid JSON encoded as UTF-16", lambda b: b.decode().encode("utf-16"))
    rv("bom", "valid JSON with a UTF-8 byte-order mark", lambda b: b"\xef\xbb\xbf" + b, "either")
    rv("deep", "JSON nested 100000 levels deep", lambda b: b"[" * 100000 + b"]" * 100000)
    rv("padded", "valid JSON followed by 20 MB of spaces", lambda b: b + b" " * 20_000_000, "ok")
    rv("trailing", "valid JSON followed by a second object", lambda b: b + b"{}")
    rv("nan_token", "K[0][0] written as the JSON token NaN",
       lambda b: re.sub(rb'"K": \[\s*\[\s*[0-9.e+-]+', b'"K": [[NaN', b, count=1))
    rv("inf_token", "t_view_from_ref_m written with Infinity",
       lambda b: re.sub(rb'("t_view_from_ref_m": \[\s*)[0-9.e+-]+', rb"\1Infinity", b, count=2))
    rv("bigint", "fx a 400-digit integer", lambda b: re.sub(rb'"K": \[\s*\[\s*[0-9.e+-]+', b'"K": [[' + b"9" * 400, b,
                                                            count=1))
    v.append(("dir", "the calibration path is a folder", mkdirs("c.json"), "error"))
    v.append(("fifo", "the calibration path is a FIFO with no writer", fifo("c.json"), "error"))
    v.append(("devnull", "the calibration path is a character device (null)", device("c.json"), "error"))
    v.append(("symlink_ok", "the calibration path is a symlink to a valid file",
              chain(use("real.json=cal.json"), symlink("c.json", "real.json")), "ok"))
    v.append(("dangling", "dangling symlink", symlink("c.json", "nowhere.json"), "error"))
    v.append(("loop", "symlink loop", chain(symlink("c.json", "c2.json"), symlink("c2.json", "c.json")), "error"))
    jv("toplist", "top level is a list", lambda d: Replace([d]))
    jv("topnull", "top level is null", lambda d: Replace(None))
    jv("topnum", "top level is a number", lambda d: Replace(42))
    jv("format_missing", "format missing", D("format"))
    jv("format_wrong", "format 'opencv'", S("format", "opencv"))
    jv("version2", "version 2", S("version", 2))
    jv("version_str", "version '1' (a string)", S("version", "1"))
    jv("version_float", "version 1.0 (a float equal to 1)", S("version", 1.0), "either")
    jv("grid_missing", "grid missing", D("grid"))
    jv("grid_list", "grid is [2, 2]", S("grid", [2, 2]))
    jv("rows0", "grid.rows 0", S("grid", "rows", 0))
    jv("rows_neg", "grid.rows -2", S("grid", "rows", -2))
    jv("rows_float", "grid.rows 2.0", S("grid", "rows", 2.0))
    jv("rows_str", "grid.rows '2'", S("grid", "rows", "2"))
    jv("rows_bool", "grid.rows true", S("grid", "rows", True))
    jv("rows_huge", "grid.rows 10**9", S("grid", "rows", 10**9))
    jv("ref_out", "grid.reference 4 (no such view)", S("grid", "reference", 4))
    jv("ref_neg", "grid.reference -1", S("grid", "reference", -1))
    jv("ref_other", "grid.reference 1 but view 1 has a non-identity pose", S("grid", "reference", 1))
    jv("cols_missing", "grid.cols missing", D("grid", "cols"))
    jv("size_missing", "image_size_px missing", D("image_size_px"))
    jv("size_one", "image_size_px [320]", S("image_size_px", [320]))
    jv("size_three", "image_size_px [320, 240, 3]", S("image_size_px", [320, 240, 3]))
    jv("size_zero", "image_size_px [0, 240]", S("image_size_px", [0, 240]))
    jv("size_neg", "image_size_px [-320, 240]", S("image_size_px", [-320, 240]))
    jv("size_float", "image_size_px [320.5, 240]", S("image_size_px", [320.5, 240]))
    jv("size_str", "image_size_px ['320', 240]", S("image_size_px", ["320", 240]))
    jv("size_huge", "image_size_px [10**9, 10**9] (parses; no camera is that big)", S("image_size_px", [10**9, 10**9]),
       "either")
    jv("size_other", "image_size_px [640, 480] (a calibration for another image size)", S("image_size_px", [640, 480]),
       "either")
    jv("views_missing", "views missing", D("views"))
    jv("views_obj", "views is an object", S("views", {}))
    jv("views_empty", "views is []", S("views", []))
    jv("views_three", "3 views for a 2x2 grid", lambda d: d["views"].pop())
    jv("view_list", "views[1] is a list", S("views", 1, []))
    jv("view_null", "views[1] is null", S("views", 1, None))
    jv("index_missing", "views[1].index missing", D("views", 1, "index"))
    jv("index_wrong", "views[1].index 5", S("views", 1, "index", 5))
    jv("row_wrong", "views[1].row 7", S("views", 1, "row", 7))
    jv("K_missing", "views[1].K missing", D("views", 1, "K"))
    jv("K_2x2", "views[1].K 2x2", S("views", 1, "K", [[300, 0], [0, 300]]))
    jv("K_3x4", "views[1].K 3x4", S("views", 1, "K", [[300, 0, 160, 0], [0, 300, 120, 0], [0, 0, 1, 0]]))
    jv("K_flat", "views[1].K a flat list of 9", S("views", 1, "K", [300, 0, 160, 0, 300, 120, 0, 0, 1]))
    jv("K_ragged", "views[1].K ragged rows", S("views", 1, "K", [[300, 0, 160], [0, 300], [0, 0, 1]]))
    jv("K_str", "views[1].K holds strings", S("views", 1, "K", [["300", "0", "160"], ["0", "300", "120"],
                                                                 ["0", "0", "1"]]))
    jv("K_deeper", "views[1].K nested one level deeper", lambda d: setp(d, ("views", 1, "K"), [d["views"][1]["K"]]))
    jv("fx0", "fx 0", S("views", 1, "K", 0, 0, 0.0))
    jv("fx_neg", "fx -300", S("views", 1, "K", 0, 0, -300.0))
    jv("fx_nan", "fx NaN", S("views", 1, "K", 0, 0, NAN))
    jv("fx_inf", "fx Infinity", S("views", 1, "K", 0, 0, INF))
    jv("fx_huge", "fx 1e308", S("views", 1, "K", 0, 0, 1e308), "either")
    jv("fx_tiny", "fx 1e-300", S("views", 1, "K", 0, 0, 1e-300), "either")
    jv("skew", "K[0][1] skew 1.0", S("views", 1, "K", 0, 1, 1.0))
    jv("K22", "K[2][2] = 2", S("views", 1, "K", 2, 2, 2.0))
    jv("cx_far", "cx 1e9 (principal point far outside the image)", S("views", 1, "K", 0, 2, 1e9), "either")
    jv("dist_missing", "distortion missing", D("views", 1, "distortion"))
    jv("dist_list", "distortion as a list [k1, k2, p1, p2]", S("views", 1, "distortion", [0.0, 0.0, 0.0, 0.0]))
    jv("k1_missing", "distortion.k1 missing", D("views", 1, "distortion", "k1"))
    jv("k1_str", "distortion.k1 '0.1'", S("views", 1, "distortion", "k1", "0.1"))
    jv("k1_null", "distortion.k1 null", S("views", 1, "distortion", "k1", None))
    jv("k1_nan", "distortion.k1 NaN", S("views", 1, "distortion", "k1", NAN))
    jv("k1_50", "distortion.k1 50 (folds over inside the image)", S("views", 1, "distortion", "k1", 50.0), "either")
    jv("k1_m50", "distortion.k1 -50", S("views", 1, "distortion", "k1", -50.0), "either")
    jv("k2_huge", "distortion.k2 1e12", S("views", 1, "distortion", "k2", 1e12), "either")
    jv("p1_big", "distortion.p1 0.9", S("views", 1, "distortion", "p1", 0.9), "either")
    jv("k3_extra", "an extra distortion.k3", S("views", 1, "distortion", "k3", 0.01), "either")
    jv("R_missing", "views[1].R_view_from_ref missing", D("views", 1, "R_view_from_ref"))
    jv("R_2x2", "R 2x2", S("views", 1, "R_view_from_ref", [[1, 0], [0, 1]]))
    jv("R_scaled", "R = 2 I", S("views", 1, "R_view_from_ref", [[2, 0, 0], [0, 2, 0], [0, 0, 2]]))
    jv("R_reflect", "R a reflection diag(1, 1, -1)", S("views", 1, "R_view_from_ref", [[1, 0, 0], [0, 1, 0],
                                                                                      [0, 0, -1]]))
    jv("R_zero", "R all zeros", S("views", 1, "R_view_from_ref", [[0] * 3] * 3))
    jv("R_nan", "R holds NaN", S("views", 1, "R_view_from_ref", 0, 0, NAN))
    jv("R_off", "R off a rotation by 1e-3", lambda d: setp(d, ("views", 1, "R_view_from_ref", 0, 1),
                                                           d["views"][1]["R_view_from_ref"][0][1] + 1e-3))
    jv("R_6dp", "R printed to 6 decimals (R^T R off by 1.5e-6, as HALCON writes it)",
       S("views", 1, "R_view_from_ref", R_6_DECIMALS), "ok")
    jv("R_tiny_off", "R off a rotation by 1e-12", lambda d: setp(d, ("views", 1, "R_view_from_ref", 0, 1),
                                                                 d["views"][1]["R_view_from_ref"][0][1] + 1e-12), "ok")
    jv("t_missing", "views[1].t_view_from_ref_m missing", D("views", 1, "t_view_from_ref_m"))
    jv("t_two", "t has 2 elements", S("views", 1, "t_view_from_ref_m", [0.01, 0.0]))
    jv("t_huge", "t 1e300 m", S("views", 1, "t_view_from_ref_m", [1e300, 0.0, 0.0]), "either")
    jv("t_str", "t holds strings", S("views", 1, "t_view_from_ref_m", ["0.01", "0", "0"]))
    jv("t_ref", "reference view t = [0.1, 0, 0]", S("views", 0, "t_view_from_ref_m", [0.1, 0.0, 0.0]))
    jv("t_same", "every view at the reference's position (t = 0)",
       lambda d: [setp(d, ("views", i, "t_view_from_ref_m"), [0.0, 0.0, 0.0]) for i in range(4)], "either")
    jv("metrics_list", "metrics is a list", S("metrics", [1, 2]))
    jv("metrics_str", "metrics is a string", S("metrics", "good"))
    jv("metrics_null", "metrics null", S("metrics", None), "ok")
    jv("metrics_missing", "metrics missing", D("metrics"), "ok")
    jv("m_emono_str", "metrics.e_mono_px 'abc'", S("metrics", "e_mono_px", "abc"), "either")
    jv("m_emono_list", "metrics.e_mono_px [1, 2]", S("metrics", "e_mono_px", [1, 2]), "either")
    jv("m_rig_obj", "metrics.rig_rms_px {}", S("metrics", "rig_rms_px", {}), "either")
    jv("m_sigmas_str", "metrics.sigmas 'bad'", S("metrics", "sigmas", "bad"), "either")
    jv("m_sigmas_short", "metrics.sigmas with 3 entries for 4 views", lambda d: d["metrics"]["sigmas"].pop(), "either")
    jv("m_sigmas_keys", "metrics.sigmas[1] without its keys", S("metrics", "sigmas", 1, {}), "either")
    jv("m_sigmas_neg", "metrics.sigmas all negative",
       lambda d: [s.update({k: (-abs(x) if isinstance(x, float) else [-abs(y) for y in x]) for k, x in s.items()})
                  for s in d["metrics"]["sigmas"]], "either")
    jv("m_sigmas_huge", "metrics.sigmas all 1e300",
       lambda d: [s.update({k: (1e300 if isinstance(x, float) else [1e300 for _ in x]) for k, x in s.items()})
                  for s in d["metrics"]["sigmas"]], "either")
    jv("m_sigmas_zero", "metrics.sigmas all 0",
       lambda d: [s.update({k: (0.0 if isinstance(x, float) else [0.0 for _ in x]) for k, x in s.items()})
                  for s in d["metrics"]["sigmas"]], "either")
    jv("m_warnings_int", "metrics.warnings 5", S("metrics", "warnings", 5), "either")
    jv("m_warnings_mixed", "metrics.warnings [1, {}, null]", S("metrics", "warnings", [1, {}, None]), "either")
    jv("m_coverage_str", "metrics.coverage 'x'", S("metrics", "coverage", "x"), "either")
    jv("m_frame_rms_str", "metrics.frame_rms_px 'x'", S("metrics", "frame_rms_px", "x"), "either")
    jv("m_views_rms_short", "metrics.view_rms_px with 1 entry", S("metrics", "view_rms_px", [0.1]), "either")
    jv("m_fpv_int", "metrics.frames_per_view 7", S("metrics", "frames_per_view", 7), "either")
    jv("m_outliers_str", "metrics.outlier_frames 'x'", S("metrics", "outlier_frames", "x"), "either")
    jv("rect_str", "rectification 'abc'", S("rectification", "abc"))
    jv("rect_empty", "rectification {} (stored but empty)", S("rectification", {}), "either")
    jv("rect_views", "rectification.views with 1 entry", lambda d: d["rectification"]["views"].pop(), "either",
       src="cal_rect.json")
    jv("rect_Kr_nan", "rectification.K_r holds NaN", S("rectification", "K_r", 0, 0, NAN), "either",
       src="cal_rect.json")
    jv("rect_crop", "rectification.crop 'bogus'", S("rectification", "crop", "bogus"), "either", src="cal_rect.json")
    jv("rect_size0", "rectification.image_size_px [0, 0]", S("rectification", "image_size_px", [0, 0]), "either",
       src="cal_rect.json")
    jv("rect_size_huge", "rectification.image_size_px [100000, 100000]",
       S("rectification", "image_size_px", [100000, 100000]), "either", src="cal_rect.json")
    jv("rect_R_bad", "rectification.views[1].R_rect_from_view all zeros",
       S("rectification", "views", 1, "R_rect_from_view", [[0] * 3] * 3), "either", src="cal_rect.json")
    jv("rect_ok", "a calibration with its rectification stored (valid)", lambda d: None, "ok", src="cal_rect.json")
    return v


# variants run through the commands that consume a calibration (the rest only through `info`)
DOWNSTREAM = ("garbage", "deep", "fifo", "fx_huge", "fx_tiny", "cx_far", "k1_50", "k1_m50", "k2_huge", "p1_big",
              "t_huge", "t_same", "size_huge", "size_other", "m_sigmas_str", "m_sigmas_neg", "m_sigmas_huge",
              "m_sigmas_zero", "m_emono_str", "rect_empty", "rect_views", "rect_Kr_nan", "rect_crop", "rect_size0",
              "rect_size_huge", "rect_R_bad", "rect_ok", "bom", "version_float")


GOOD_GEOMETRY = {k for k in DOWNSTREAM if k.startswith(("m_", "rect_"))} | {"bom", "version_float"}


def build_cases() -> list[Case]:
    cases: list[Case] = []

    def add(c: Case) -> None:
        if "fifo" in c.id and c.timeout == DEFAULT_TIMEOUT_S:
            c.timeout = FIFO_TIMEOUT_S  # a read of a FIFO nobody writes blocks forever: 15 s shows it
        cases.append(c)

    def cli(id_: str, command: str, desc: str, argv: list[str], setup=None, expect="error", **kw) -> None:
        add(Case(id_, command, desc, "cli", [str(a) for a in argv], setup=setup, expect=expect, **kw))

    def api(id_: str, command: str, desc: str, code: str, setup=None, expect="error", **kw) -> None:
        code = textwrap.dedent(code)
        compile(code, id_, "exec")  # a snippet that does not even compile is the trial's bug, not lfgraph's
        add(Case(id_, "api:" + command, desc, "api", code=code, setup=setup, expect=expect, **kw))

    # ------------------------------------------------------------------ usage
    cli("usage-noargs", "usage", "no command", [])
    cli("usage-unknown", "usage", "unknown command", ["bogus"])
    cli("usage-version", "usage", "--version", ["--version"], expect="ok")
    cli("usage-v-q", "usage", "-v and -q together", ["-v", "-q", "info", "c.json"], use("c.json=cal.json"))
    cli("usage-noinput", "usage", "info without its argument", ["info"])
    cli("usage-badflag", "usage", "an unknown flag", ["info", "c.json", "--bogus"], use("c.json=cal.json"))
    cli("usage-help", "usage", "calibrate --help", ["calibrate", "--help"], expect="ok")
    cli("usage-empty-arg", "usage", "info ''", ["info", ""])

    # ------------------------------------------------------------------ calibration files: info (all variants)
    variants = _cal_variants()
    for key, desc, setup, expect in variants:
        chk = None
        if expect != "error":
            chk = lambda case, d, res: (("r00_c00" in res.stdout or "view" in res.stdout), "printed the views")  # noqa: E731
        cli(f"info-{key}", "info", desc, ["info", "c.json"], setup, expect, check=chk)
    for key in ("fx_huge", "t_huge", "m_sigmas_huge", "m_emono_str", "size_huge", "rect_ok", "cx_far", "k2_huge"):
        key_, desc, setup, expect = next(x for x in variants if x[0] == key)
        cli(f"infojson-{key}", "info", f"--json: {desc}", ["info", "c.json", "--json"], setup, expect,
            check=strict_json_stdout())
    vmap = {k: (desc, s, e) for k, desc, s, e in variants}
    cli("info-12views-R6dp", "info", "a 3x4 calibration whose views[5] rotation is printed to 6 decimals (as reported)",
        ["info", "c.json"], twelve_views_printed("c.json"), "ok",
        check=lambda case, d, res: ("r02_c03" in res.stdout, "printed the 12 views"))

    # ------------------------------------------------------------------ calibration files downstream
    for key in DOWNSTREAM:
        desc, setup, expect = vmap[key]
        good_geometry = key in GOOD_GEOMETRY
        bad = expect == "error" or key.startswith("size_")
        exp = "error" if bad else "either"
        cli(f"rectify-cal-{key}", "rectify", f"calibration: {desc}", ["rectify", "c.json", "cb", "-o", "rect", *Q],
            chain(use("cb"), setup), exp, check=rectified_check("rect", 8))
        cli(f"check-cal-{key}", "check", f"calibration: {desc}", ["check", "c.json", "sc_still", "--json"],
            chain(use("sc_still"), setup), exp, ok_codes=(0, 3),
            check=all_of(strict_json_stdout(), rc_is(0, "the rig did not move") if good_geometry else
                         not_ok_verdict("the calibration is absurd for these images")))
        cli(f"refine-cal-{key}", "refine", f"calibration: {desc}", ["refine", "c.json", "sc", "-o", "r.json",
                                                                   "--quiet"],
            chain(use("sc"), setup), exp,
            check=not_worse("r.json", "c.json", "sc/truth.json") if good_geometry else loads_check("r.json"))
    for key in ("garbage", "fx_huge", "k1_50", "t_huge", "m_sigmas_huge", "rect_Kr_nan", "size_huge", "bom"):
        desc, setup, expect = vmap[key]
        for fmt, out in (("opencv-yaml", "x.yaml"), ("kalibr", "x.yaml"), ("colmap", "xcolmap"), ("json", "x.json")):
            cli(f"export-cal-{key}-{fmt}", "export", f"calibration: {desc}", ["export", "c.json", "--to", fmt, "-o", out],
                setup, "either" if expect != "error" else "error", check=roundtrip_check(out, fmt, "c.json"))
    for key in ("garbage", "fx_huge", "t_huge", "size_other", "rows_huge", "deep", "m_emono_str", "fx_tiny"):
        desc, setup, expect = vmap[key]
        cli(f"evaluate-cal-{key}", "evaluate", f"calibration: {desc}",
            ["evaluate", "c.json", "--truth", "truth.json", "--json"],
            chain(use("truth.json=cb/truth.json"), setup), "either" if expect != "error" else "error",
            check=strict_json_stdout())
        cli(f"evaluate-truth-{key}", "evaluate", f"truth: {desc}",
            ["evaluate", "cal.json", "--truth", "c.json", "--json"],
            chain(use("cal.json"), setup), "either" if expect != "error" else "error", check=strict_json_stdout())

    # ------------------------------------------------------------------ calibrate
    good = calib_close("o.json", "cb/truth.json")
    C = ["calibrate", "cb", *CALARGS, "-o", "o.json", *Q]  # noqa: N806

    def cal(id_, desc, extra=(), setup=None, expect="error", argv=None, **kw):
        a = argv if argv is not None else [*C, *extra]
        cli(f"calibrate-{id_}", "calibrate", desc, a, chain(use("cb"), setup), expect, **kw)

    cal("valid", "valid small capture (baseline)", expect="ok", check=good)
    for g in ("2x3", "3x3", "1x2", "2x1", "1x1", "0x2", "2x0", "abc", "2x2x2", "-2x2", "1000x1000", "2X2", " 2x2 ",
              "99999999999999999999x2", "", "4"):
        cal(f"grid-{re.sub(r'[^0-9a-zA-Z]', '_', g) or 'empty'}", f"--grid {g!r} on a 2x2 capture",
            argv=["calibrate", "cb", "--grid", g, *BOARD, "-o", "o.json", *Q],
            expect="either" if g.strip().lower() == "2x2" else "error", check=good)
    for b in ("5x7", "8x5", "6x5", "7x6", "6x4", "11x8", "2x2", "1x1", "0x0", "-7x5", "7x5x3", "abc", "100x100", "7 x 5",
              "charuco:4x5:DICT_4X4_1000", "charuco:bad", "charuco:4x5:DICT_BOGUS"):
        cal(f"board-{re.sub(r'[^0-9a-zA-Z]', '_', b)}", f"--board {b!r} (the images hold a 7x5 board)",
            argv=["calibrate", "cb", "--grid", "2x2", "--board", b, "--square-mm", "15", "-o", "o.json", *Q],
            expect="either" if b in ("5x7", "7 x 5") else "error", check=good)
    cal("charuco-marker", "--board charuco:4x5:DICT_4X4_1000 --marker-mm 10 on chessboard images",
        argv=["calibrate", "cb", "--grid", "2x2", "--board", "charuco:4x5:DICT_4X4_1000", "--square-mm", "15",
              "--marker-mm", "10", "-o", "o.json", *Q])
    cal("charuco-marker-big", "ChArUco --marker-mm 20 larger than the 15 mm square",
        argv=["calibrate", "cb", "--grid", "2x2", "--board", "charuco:4x5:DICT_4X4_1000", "--square-mm", "15",
              "--marker-mm", "20", "-o", "o.json", *Q])
    cal("marker-on-chessboard", "--marker-mm with a plain checkerboard", ["--marker-mm", "10"], expect="either",
        check=good)
    for sq in ("0", "-15", "nan", "inf", "1e308", "1e-300", "abc"):
        cal(f"square-{sq.replace('-', 'm').replace('.', '_')}", f"--square-mm {sq}",
            argv=["calibrate", "cb", "--grid", "2x2", "--board", "7x5", "--square-mm", sq, "-o", "o.json", *Q],
            expect="error")
    cal("square-missing", "--board without --square-mm",
        argv=["calibrate", "cb", "--grid", "2x2", "--board", "7x5", "-o", "o.json", *Q])
    cal("board-missing", "no --board", argv=["calibrate", "cb", "--grid", "2x2", "-o", "o.json", *Q])
    for r in ("3", "4", "-1", "99", "x"):
        cal(f"reference-{r.replace('-', 'm')}", f"--reference {r}", ["--reference", r],
            expect="ok" if r == "3" else "error",
            check=exists_check("o.json") if r == "3" else None)
    cal("method-bogus", "--method bogus", ["--method", "bogus"])
    cal("method-paper", "--method paper (valid)", ["--method", "paper"], expect="ok",
        check=calib_close("o.json", "cb/truth.json", 5.0, 2.0, 0.5))
    cal("init-design", "--init design (valid)", ["--init", "design"], expect="ok", check=good)
    for fp in ("0", "nan", "-5", "1e9", "1"):
        cal(f"focal-{fp.replace('-', 'm')}", f"--init design --focal-px {fp}", ["--init", "design", "--focal-px", fp],
            expect="error" if fp in ("0", "nan", "-5") else "either", check=good)
    for pm in ("0", "1e9"):
        cal(f"pitch-{pm}", f"--init design --pitch-mm {pm}", ["--init", "design", "--pitch-mm", pm],
            expect="error" if pm == "0" else "either", check=good)
    for rb in ("huber:1", "bogus", "huber:-1", "huber:0", "huber:nan", "huber:inf", "huber:", ":1", "huber:1:2",
               "HUBER:1", "tukey:1e-300", "cauchy:1e308", "gm", "dcs", "none", " huber : 1 "):
        valid = rb in ("huber:1", "HUBER:1", "gm", "dcs", "none", "huber:", "cauchy:1e308", "tukey:1e-300")
        cal(f"robust-{re.sub(r'[^0-9a-zA-Z]', '_', rb)}", f"--robust {rb!r}", ["--robust", rb],
            expect="either" if valid else "error", check=good)
    for bs in ("0", "-1", "nan", "1", "1e9"):
        cal(f"boardsigma-{bs.replace('-', 'm')}", f"--board-sigma-mm {bs}", ["--board-sigma-mm", bs],
            expect="either" if bs in ("1", "1e9") else "error", check=good)
    cal("tangential", "--tangential (valid)", ["--tangential"], expect="ok", check=good)
    for j in ("0", "-1", "abc"):
        cal(f"jobs-{j.replace('-', 'm')}", f"--jobs {j}",
            argv=["calibrate", "cb", *CALARGS, "-o", "o.json", "--jobs", j, "--quiet"])
    cal("jobs-64", "--jobs 64 on 2 cores (capped by the tasks)",
        argv=["calibrate", "cb", *CALARGS, "-o", "o.json", "--jobs", "64", "--quiet", "--no-cache"], expect="ok",
        check=good)
    for lay in ("mosaic", "hci", "pairs", "video", "views", "bogus"):
        cal(f"layout-{lay}", f"--layout {lay} on a folders capture", ["--layout", lay],
            expect="either" if lay == "hci" else "error", check=good)
    cal("missingview-bogus", "--missing-view bogus", ["--missing-view", "bogus"])
    cal("image-size-images", "--image-size with image input (meant for --detections)", ["--image-size", "100x100"],
        expect="either", check=good)
    cal("no-cache", "--no-cache (valid)", ["--no-cache"], expect="ok", check=good)
    # the detection cache in place is not a regular file: ignored with a warning, never read nor replaced
    cal("cache-fifo", "INPUT/.lfgraph-detections.npz is a FIFO nobody writes", setup=fifo("cb/.lfgraph-detections.npz"),
        expect="ok", check=all_of(good, still_special("cb/.lfgraph-detections.npz")))
    cal("cache-device", "INPUT/.lfgraph-detections.npz is a character device (an endless zero device)",
        setup=chain(remove("cb/.lfgraph-detections.npz"), device("cb/.lfgraph-detections.npz", 1, 5)), expect="ok",
        check=all_of(good, still_special("cb/.lfgraph-detections.npz")))
    # outputs
    o = ["calibrate", "cb", *CALARGS, *Q]
    cal("out-is-image", "-o is an input image", argv=[*o, "-o", "cb/000/r00_c00.png"])
    cal("out-is-input-dir", "-o is the input folder", argv=[*o, "-o", "cb"])
    cal("out-missing-dir", "-o in a folder that does not exist", argv=[*o, "-o", "nope/o.json"])
    cal("out-symlink-new", "-o is a symlink to a new file", argv=[*o, "-o", "link.json"],
        setup=symlink("link.json", "target.json"))
    cal("out-symlink-image", "-o is a symlink to an input image", argv=[*o, "-o", "link.json"],
        setup=symlink("link.json", "cb/000/r00_c00.png"))
    cal("out-fifo", "-o is a FIFO", argv=[*o, "-o", "f.json"], setup=fifo("f.json"))
    cal("out-devnull", "-o a null device", argv=[*o, "-o", "dev_null"], setup=device("dev_null"))
    cal("out-existing", "-o an existing file that is not an input (replaced)", argv=[*o, "-o", "old.json"],
        setup=put("old.json", "{}"), expect="ok", mutable=(r"^old\.json$",),
        check=calib_close("old.json", "cb/truth.json"))
    cal("out-empty", "-o ''", argv=[*o, "-o", ""])
    cal("out-trailing-slash", "-o 'newdir/' (a folder name; a file 'newdir' is acceptable)", argv=[*o, "-o", "newdir/"],
        expect="either", check=calib_close("newdir", "cb/truth.json"))
    cal("out-inside-input", "-o inside the capture folder (allowed by the README)", argv=[*o, "-o", "cb/o.json"],
        expect="ok", check=calib_close("cb/o.json", "cb/truth.json"))
    cal("out-truth", "-o is the capture's truth.json (not read by calibrate)", argv=[*o, "-o", "cb/truth.json"],
        expect="either", mutable=(r"truth\.json$",), check=exists_check("cb/truth.json"))
    # --save / --plots
    cal("save-valid", "--save run.rrd (valid)", ["--save", "run.rrd"], expect="ok",
        check=all_of(good, exists_check("run.rrd")))
    cal("save-is-output", "--save is -o", ["--save", "o.json"])
    cal("save-is-image", "--save is an input image", ["--save", "cb/000/r00_c00.png"])
    cal("save-is-dir", "--save is a folder", ["--save", "sub"], setup=mkdirs("sub"))
    cal("save-missing-dir", "--save in a missing folder", ["--save", "nope/run.rrd"])
    cal("save-fifo", "--save is a FIFO", ["--save", "f.rrd"], setup=fifo("f.rrd"))
    cal("save-symlink", "--save is a symlink", ["--save", "l.rrd"], setup=symlink("l.rrd", "t.rrd"))
    cal("save-devnull", "--save a null device", ["--save", "dev_null"], setup=device("dev_null"))
    cal("connect-none", "--connect with no viewer listening", ["--connect", "--url", "rerun+http://127.0.0.1:1/proxy"])
    cal("url-garbage", "--connect --url garbage", ["--connect", "--url", "garbage"])
    cal("plots-valid", "--plots figs (valid)", ["--plots", "figs"], expect="ok",
        check=all_of(good, exists_check("figs", min_files=2)))
    cal("plots-inside-input", "--plots inside the input", ["--plots", "cb/figs"])
    cal("plots-is-output", "--plots is -o", ["--plots", "o.json"])
    cal("plots-is-file", "--plots is an existing file", ["--plots", "f.txt"], setup=put("f.txt", "keep me"))
    cal("plots-nonempty", "--plots an existing folder holding a user's file", ["--plots", "figs"],
        setup=put("figs/notes.txt", "keep me"), expect="ok", check=all_of(good, exists_check("figs", min_files=3)))
    cal("plots-is-save", "--plots and --save the same path", ["--plots", "x.rrd", "--save", "x.rrd"])
    cal("plots-devnull", "--plots a null device", ["--plots", "dev_null"], setup=device("dev_null"))
    # images
    import cv2

    # a rig whose streams are wrong (issue 42, third round): refused by name, or re-labelled by --view-order
    def swap_streams(d: Path) -> None:
        for fd in frame_dirs(d / "cb"):
            a, b = fd / "r00_c00.png", fd / "r00_c01.png"
            data = a.read_bytes()
            a.write_bytes(b.read_bytes())
            b.write_bytes(data)

    def duplicate_stream(d: Path) -> None:
        for fd in frame_dirs(d / "cb"):
            (fd / "r00_c01.png").write_bytes((fd / "r00_c00.png").read_bytes())

    cal("streams-swapped", "r00_c00 and r00_c01 swapped in every frame (cables swapped)", setup=swap_streams)
    cal("streams-swapped-view-order", "the swapped capture with --view-order naming the true order",
        ["--view-order", "r00_c01,r00_c00,r01_c00,r01_c01"], setup=swap_streams, expect="ok", check=good)
    cal("streams-duplicated", "r00_c01 a copy of r00_c00 in every frame (one stream duplicated)",
        setup=duplicate_stream)
    cal("streams-mirrored", "r00_c01 mirrored left-right in every frame (a camera's flip option)",
        setup=images("cb", lambda im, f, v: im[:, ::-1].copy(), views=(1,)))
    cal("view-order-short", "--view-order naming three of four views", ["--view-order", "r00_c01,r00_c00,r01_c00"])
    cal("lens-two-defaults", "--lens fisheye,radtan (two defaults)", ["--lens", "fisheye,radtan"])
    cal("lens-view-twice", "--lens naming a view twice", ["--lens", "fisheye,r00_c00=fisheye,r00_c00=radtan"])
    cal("lens-fisheye-tangential", "--lens fisheye --tangential (fisheye has no p1, p2)",
        ["--lens", "fisheye", "--tangential"])
    cal("img-uint16", "every image 16-bit (x257)", setup=images("cb", lambda im, f, v: im.astype(np.uint16) * 257),
        expect="either", check=good)
    cal("img-uint16-one", "one view's images 16-bit", setup=images("cb", lambda im, f, v: im.astype(np.uint16) * 257,
                                                                    views=(1,)), expect="either", check=good)
    cal("img-float-tiff", "every image a 32-bit float TIFF in 0..1 (.tiff names)",
        setup=images("cb", lambda im, f, v: im.astype(np.float32) / 255, ext=".tiff"), expect="either", check=good)
    cal("img-colour", "every image BGR colour", setup=images("cb", lambda im, f, v: cv2.cvtColor(im, cv2.COLOR_GRAY2BGR)),
        expect="either", check=good)
    cal("img-rgba", "every image BGRA with alpha",
        setup=images("cb", lambda im, f, v: cv2.cvtColor(im, cv2.COLOR_GRAY2BGRA)), expect="either", check=good)
    cal("img-one-resized", "one view of one frame resized to 300x200",
        setup=images("cb", lambda im, f, v: cv2.resize(im, (300, 200)), frames=(3,), views=(2,)))
    cal("img-first-resized", "one view of the first frame resized to 300x200",
        setup=images("cb", lambda im, f, v: cv2.resize(im, (300, 200)), frames=(0,), views=(2,)))
    cal("img-all-resized", "every image 640x480 (upscaled; a consistent capture)",
        setup=images("cb", lambda im, f, v: cv2.resize(im, (640, 480), interpolation=cv2.INTER_CUBIC)),
        expect="either", check=loads_check("o.json"))
    for name, fn in (("zero", _zero), ("truncated", _truncate), ("garbage", _garbage), ("text", _text),
                     ("dir", _to_dir), ("dangling", _dangling), ("fifo", _to_fifo)):
        cal(f"img-{name}-first", f"frame 0 view 0: {name} instead of a PNG", setup=file_op("cb", fn, (0,), (0,)))
        cal(f"img-{name}-later", f"frame 5 view 2: {name} instead of a PNG", setup=file_op("cb", fn, (5,), (2,)))
    cal("img-jpeg-as-png", "JPEG bytes under .png names", setup=file_op("cb", _jpeg_in_png, None, None),
        expect="either", check=good)
    cal("img-1x1", "every image 1x1 px", setup=images("cb", lambda im, f, v: im[:1, :1]))
    cal("img-black", "every image black (no board anywhere)", setup=images("cb", lambda im, f, v: im * 0))
    cal("img-black-frame", "frame 2 black in every view", setup=images("cb", lambda im, f, v: im * 0, frames=(2,)),
        expect="either", check=good)
    cal("img-view-never", "view 3 black in every frame (never sees the board)",
        setup=images("cb", lambda im, f, v: im * 0, views=(3,)))
    cal("img-noise", "every image uniform noise",
        setup=images("cb", lambda im, f, v: np.random.default_rng(f * 4 + v).integers(0, 256, im.shape, np.uint8)))
    cal("img-missing-view", "frame 4 lacks view 1", setup=remove("cb/004/r00_c01.png"))
    cal("img-missing-unseen", "frame 4 lacks view 1, --missing-view unseen", ["--missing-view", "unseen"],
        setup=remove("cb/004/r00_c01.png"), expect="ok", check=good)
    cal("img-extra-view", "frame 4 holds an extra r02_c00.png", setup=use("cb/004/r02_c00.png=cb/004/r00_c00.png"),
        expect="either", check=good)
    cal("img-extra-file", "a notes.txt inside frame 4", setup=put("cb/004/notes.txt", "hello"), expect="either",
        check=good)
    cal("img-hidden-file", "a .DS_Store inside frame 4 and the capture", setup=chain(
        put("cb/004/.DS_Store", b"\0\0\0\1Bud1"), put("cb/.DS_Store", b"\0\0\0\1Bud1")), expect="ok", check=good)
    cal("frames-zero", "an empty capture folder", argv=["calibrate", "empty", *CALARGS, "-o", "o.json", *Q],
        setup=mkdirs("empty"))
    cal("frames-truth-only", "a capture folder with truth files but no frames", setup=remove(
        *[f"cb/{i:03d}" for i in range(8)]))
    cal("frames-one", "one frame", setup=remove(*[f"cb/{i:03d}" for i in range(1, 8)]), expect="either",
        check=calib_close("o.json", "cb/truth.json", 10.0, 3.0, 1.0))
    cal("frames-two", "two frames", setup=remove(*[f"cb/{i:03d}" for i in range(2, 8)]), expect="either",
        check=calib_close("o.json", "cb/truth.json", 10.0, 3.0, 1.0))
    cal("frames-dup", "every frame duplicated (16 frames)",
        setup=lambda d: [shutil.copytree(d / f"cb/{i:03d}", d / f"cb/{i + 8:03d}") for i in range(8)], expect="ok",
        check=good)
    cal("frames-all-same", "8 copies of frame 0 (one board pose)",
        setup=lambda d: [(shutil.rmtree(d / f"cb/{i:03d}"), shutil.copytree(d / "cb/000", d / f"cb/{i:03d}"))
                         for i in range(1, 8)], expect="error", check=good)
    cal("views-swapped", "views r00_c01 and r01_c00 swapped in frame 3 only",
        setup=lambda d: [os.rename(d / "cb/003/r00_c01.png", d / "cb/003/tmp.png"),
                         os.rename(d / "cb/003/r01_c00.png", d / "cb/003/r00_c01.png"),
                         os.rename(d / "cb/003/tmp.png", d / "cb/003/r01_c00.png")], expect="either", check=good)
    cal("view-copy", "frame 3: view 1's image replaced by view 0's", setup=use("cb/003/r00_c01.png=cb/003/r00_c00.png"),
        expect="either", check=good)
    cal("input-is-file", "INPUT is a file", argv=["calibrate", "cal.json", *CALARGS, "-o", "o.json", *Q],
        setup=use("cal.json"))
    cal("input-missing", "INPUT does not exist", argv=["calibrate", "nope", *CALARGS, "-o", "o.json", *Q])
    cal("input-devnull", "INPUT a null device", argv=["calibrate", "dev_null", *CALARGS, "-o", "o.json", *Q],
        setup=device("dev_null"))
    cal("input-symlink", "INPUT a symlink to the capture", argv=["calibrate", "lcb", *CALARGS, "-o", "o.json", *Q],
        setup=symlink("lcb", "cb"), expect="ok", check=good)
    cal("mosaic-valid", "mosaic layout (valid)", argv=["calibrate", "cb_mosaic", *CALARGS, "-o", "o.json", *Q],
        setup=use("cb_mosaic"), expect="ok", check=good)
    cal("mosaic-grid3", "mosaic with --grid 3x3 (640x480 does not divide)",
        argv=["calibrate", "cb_mosaic", "--grid", "3x3", *BOARD, "-o", "o.json", *Q], setup=use("cb_mosaic"))
    cal("mosaic-grid14", "mosaic with --grid 1x4 (divides into 160x480 strips)",
        argv=["calibrate", "cb_mosaic", "--grid", "1x4", *BOARD, "-o", "o.json", *Q], setup=use("cb_mosaic"))
    cal("mosaic-one-size", "mosaic: one frame resized to 642x480",
        argv=["calibrate", "cb_mosaic", *CALARGS, "-o", "o.json", *Q],
        setup=chain(use("cb_mosaic"), lambda d: cv2.imwrite(str(d / "cb_mosaic/003.png"), cv2.resize(
            cv2.imread(str(d / "cb_mosaic/003.png"), 0), (642, 480)))))
    cal("hci-valid", "hci layout (valid)", argv=["calibrate", "cb_hci", *CALARGS, "-o", "o.json", *Q],
        setup=use("cb_hci"), expect="ok", check=good)
    cal("video-valid", "video layout, one MJPG .avi per view (valid)",
        argv=["calibrate", "cb_video", *CALARGS, "-o", "o.json", *Q], setup=use("cb_video"), expect="ok", check=good)
    cal("video-zero", "video layout, one video 0 bytes",
        argv=["calibrate", "cb_video", *CALARGS, "-o", "o.json", *Q], setup=chain(use("cb_video"),
                                                                                 put("cb_video/cam_2.avi", b"")))
    cal("video-truncated", "video layout, one video truncated to half",
        argv=["calibrate", "cb_video", *CALARGS, "-o", "o.json", *Q],
        setup=chain(use("cb_video"), lambda d: _truncate(d / "cb_video/cam_1.avi")), expect="either", check=good)
    cal("video-garbage", "video layout, one video is text",
        argv=["calibrate", "cb_video", *CALARGS, "-o", "o.json", *Q],
        setup=chain(use("cb_video"), put("cb_video/cam_3.avi", "not a video\n")))
    cal("video-three", "video layout, 3 videos for a 2x2 grid",
        argv=["calibrate", "cb_video", *CALARGS, "-o", "o.json", *Q], setup=chain(use("cb_video"),
                                                                                 remove("cb_video/cam_3.avi")))
    # detections from other tools
    N = ["calibrate", "p.npz", "--detections", "npz", "--grid", "2x2", "--image-size", "320x240", "-o", "o.json"]  # noqa: N806

    def npz_variant(mut):
        def f(d: Path) -> None:
            with np.load(DATA / "points.npz") as z:
                arrays = {k: z[k] for k in z.files}
            mut(arrays)
            np.savez(d / "p.npz", **arrays)
        return f

    cli("calibrate-npz-valid", "calibrate", "--detections npz (valid)", N, chain(use("cb"), use("p.npz=points.npz")),
        "ok", check=good)
    cli("calibrate-npz-objpoints", "calibrate", "--detections npz with --object-points", [*N, "--object-points",
                                                                                      "obj.npy"],
        use("p.npz=points.npz", "obj.npy"))
    cli("calibrate-npz-noimagesize", "calibrate", "--detections npz without --image-size",
        ["calibrate", "p.npz", "--detections", "npz", "--grid", "2x2", "-o", "o.json"], use("p.npz=points.npz"))
    cli("calibrate-npz-size0", "calibrate", "--image-size 0x0",
        ["calibrate", "p.npz", "--detections", "npz", "--grid", "2x2", "--image-size", "0x0", "-o", "o.json"],
        use("p.npz=points.npz"))
    cli("calibrate-npz-size-small", "calibrate", "--image-size 100x100 (points fall outside)",
        ["calibrate", "p.npz", "--detections", "npz", "--grid", "2x2", "--image-size", "100x100", "-o", "o.json"],
        use("p.npz=points.npz"))
    cli("calibrate-npz-grid", "calibrate", "--detections npz with --grid 3x3", [*N[:4], "--grid", "3x3", *N[6:]],
        use("p.npz=points.npz"))
    for key, desc, mut in (
            ("nokey", "image_points missing", lambda a: a.pop("image_points")),
            ("shape", "image_points (V, F, C) without the xy axis", lambda a: a.update(image_points=a["image_points"][..., 0])),
            ("nan-valid", "NaN at a point marked valid", lambda a: a["image_points"].__setitem__((1, 2, 3), np.nan)),
            ("all-invalid", "valid all False", lambda a: a.update(valid=np.zeros_like(a["valid"]))),
            ("nonplanar", "object points not planar", lambda a: a["object_points"].__setitem__((5, 2), 0.01)),
            ("mm", "object points in millimetres", lambda a: a.update(object_points=a["object_points"] * 1000)),
            ("outside", "a point outside the image", lambda a: a["image_points"].__setitem__((0, 0, 0), [5000.0, 5.0])),
            ("views3", "3 views for a 2x2 grid", lambda a: a.update(image_points=a["image_points"][:3],
                                                                     valid=a["valid"][:3])),
            ("valid-float", "valid as floats 0.5", lambda a: a.update(valid=a["valid"] * 0.5)),
            ("obj-nan", "object points NaN", lambda a: a["object_points"].__setitem__((0, 0), np.nan)),
            ("obj-same", "every object point at the origin", lambda a: a.update(object_points=a["object_points"] * 0)),
            ("one-frame", "only frame 0 valid", lambda a: a["valid"].__setitem__((slice(None), slice(1, None)), False)),
            ("strings", "image_points as strings", lambda a: a.update(image_points=a["image_points"].astype(str))),
            ("frames0", "zero frames", lambda a: a.update(image_points=a["image_points"][:, :0], valid=a["valid"][:, :0])),
    ):
        cli(f"calibrate-npz-{key}", "calibrate", f"--detections npz: {desc}", N, chain(use("cb"), npz_variant(mut)),
            "either" if key in ("one-frame",) else "error", check=calib_close("o.json", "cb/truth.json", 10, 3, 1))
    cli("calibrate-npz-garbage", "calibrate", "--detections npz: not a zip", N, put("p.npz", b"PK\x03\x04garbage"))
    cli("calibrate-npz-pickle", "calibrate", "--detections npz: object arrays (needs pickle)", N,
        lambda d: np.savez(d / "p.npz", object_points=np.array([None, 1], dtype=object),
                           image_points=np.zeros(1), valid=np.zeros(1)))
    MV = ["calibrate", "mv", "--detections", "opencv-multiview", "--object-points", "obj.npy", "--grid", "2x2",  # noqa: N806
          "--image-size", "320x240", "-o", "o.json"]
    cli("calibrate-mv-valid", "calibrate", "--detections opencv-multiview (valid)", MV, use("cb", "mv", "obj.npy"), "ok",
        check=good)
    cli("calibrate-mv-noobj", "calibrate", "opencv-multiview without --object-points",
        [a for a in MV if a not in ("--object-points", "obj.npy")], use("mv"))
    cli("calibrate-mv-obj-garbage", "calibrate", "opencv-multiview: obj.npy garbage", MV,
        chain(use("mv"), put("obj.npy", b"\x93NUMPYgarbage")))
    cli("calibrate-mv-obj-2d", "calibrate", "opencv-multiview: obj.npy (C, 2)", MV,
        chain(use("mv"), lambda d: np.save(d / "obj.npy", np.load(DATA / "obj.npy")[:, :2])))
    cli("calibrate-mv-obj-mm", "calibrate", "opencv-multiview: obj.npy in millimetres", MV,
        chain(use("mv"), lambda d: np.save(d / "obj.npy", np.load(DATA / "obj.npy") * 1000)))
    cli("calibrate-mv-obj-short", "calibrate", "opencv-multiview: obj.npy with 10 points (files have 35)", MV,
        chain(use("mv"), lambda d: np.save(d / "obj.npy", np.load(DATA / "obj.npy")[:10])))
    cli("calibrate-mv-json-garbage", "calibrate", "opencv-multiview: cam_1.json garbage", MV,
        chain(use("mv", "obj.npy"), put("mv/cam_1.json", "{\"frame_0\": [1, 2,, }")))
    cli("calibrate-mv-json-binary", "calibrate", "opencv-multiview: cam_1.json binary", MV,
        chain(use("mv", "obj.npy"), put("mv/cam_1.json", bytes(range(256)) * 4)))
    cli("calibrate-mv-json-strings", "calibrate", "opencv-multiview: a node of strings", MV,
        chain(use("mv", "obj.npy"), put("mv/cam_1.json", json.dumps({"frame_0": ["a"] * 70}))))
    cli("calibrate-mv-json-count", "calibrate", "opencv-multiview: a node with 3 numbers", MV,
        chain(use("mv", "obj.npy"), put("mv/cam_1.json", json.dumps({"frame_0": [1, 2, 3]}))))
    cli("calibrate-mv-json-empty", "calibrate", "opencv-multiview: cam_1.json empty file", MV,
        chain(use("mv", "obj.npy"), put("mv/cam_1.json", b"")))
    cli("calibrate-mv-three", "calibrate", "opencv-multiview: 3 files for a 2x2 grid", MV,
        chain(use("mv", "obj.npy"), remove("mv/cam_3.json")))
    cli("calibrate-mv-empty", "calibrate", "opencv-multiview: empty folder", MV, chain(use("obj.npy"), mkdirs("mv")))
    cli("calibrate-mv-deep", "calibrate", "opencv-multiview: a node nested 100000 deep", MV,
        chain(use("mv", "obj.npy"), put("mv/cam_1.json", "{\"frame_0\": " + "[" * 100000 + "]" * 100000 + "}")))

    # ------------------------------------------------------------------ calibrate-scene
    CS = ["calibrate-scene", "sc6", "--grid", "2x2", "--pitch-mm", "10", "--focal-px", "300", "-o", "o.json",  # noqa: N806
          "--quiet"]
    cs_good = calib_close("o.json", "sc6/truth.json", 15.0, 2.0, 0.5)

    def cs(id_, desc, extra=(), setup=None, expect="error", argv=None, **kw):
        a = argv if argv is not None else [*CS, *extra]
        cli(f"calscene-{id_}", "calibrate-scene", desc, a, chain(use("sc6"), setup), expect, **kw)

    cs("valid3", "valid: 6-frame scene capture, --max-frames 3", ["--max-frames", "3"], expect="ok", check=cs_good)
    cs("valid4", "valid: --max-frames 4", ["--max-frames", "4"], expect="ok", check=cs_good)
    cs("valid6", "valid: all 6 frames of a small-2x2 scene capture", expect="ok", check=cs_good)
    for flag, vals in (("--pitch-mm", ("0", "-1", "nan", "1e9")), ("--focal-px", ("0", "nan", "-1", "1e9")),
                       ("--max-frames", ("0", "1")), ("--tracks-per-frame", ("0", "1", "1000000000")),
                       ("--focal-tolerance-pct", ("0", "-1", "nan", "1e9")), ("--principal-tolerance-px", ("0",)),
                       ("--rotation-tolerance-deg", ("1e9",)), ("--position-tolerance-mm", ("0",)),
                       ("--reference", ("5", "-1"))):
        for val in vals:
            a = [x for x in CS]
            if flag in a:
                i = a.index(flag)
                a[i + 1] = val
            else:
                a += [flag, val, "--max-frames", "3"] if flag != "--max-frames" else [flag, val]
            huge_ok = val in ("1e9", "1000000000") and flag in ("--tracks-per-frame", "--rotation-tolerance-deg",
                                                                "--focal-tolerance-pct")
            # without a focal prior the zoom is free: the report's fx sigma is ~20 px, so allow 3 of those
            loose = calib_close("o.json", "sc6/truth.json", 60.0, 2.0, 0.5) if flag == "--focal-tolerance-pct" else cs_good
            cs(f"{flag.strip('-')}-{val.replace('-', 'm')}", f"{flag} {val}", argv=a,
               expect="either" if huge_ok else "error", check=loose)
    base = ["calibrate-scene", "sc6", "--grid", "2x2", "--pitch-mm", "10", "-o", "o.json", "--quiet", "--max-frames", "3"]
    cs("nofocal", "neither --focal-px nor --focal-mm", argv=base)
    cs("focal-mm-only", "--focal-mm without --sensor-width-mm", argv=[*base, "--focal-mm", "8"])
    cs("both-focal", "--focal-px and --focal-mm together",
       argv=[*base, "--focal-px", "300", "--focal-mm", "8", "--sensor-width-mm", "6.4"], expect="either", check=cs_good)
    cs("sensor0", "--sensor-width-mm 0", argv=[*base, "--focal-mm", "8", "--sensor-width-mm", "0"])
    cs("report-is-output", "--report-json is -o", [*["--max-frames", "3"], "--report-json", "o.json"])
    cs("report-is-image", "--report-json is an input image", ["--max-frames", "3", "--report-json",
                                                              "sc6/000/r00_c00.png"])
    cs("report-missing-dir", "--report-json in a missing folder", ["--max-frames", "3", "--report-json", "nope/r.json"])
    cs("report-fifo", "--report-json is a FIFO", ["--max-frames", "3", "--report-json", "r.json"], setup=fifo("r.json"))
    cs("crop-bogus", "--crop bogus", ["--crop", "bogus"])
    cs("grid-3x3", "--grid 3x3 on a 2x2 capture", argv=[*CS[:2], "--grid", "3x3", *CS[4:]])
    cs("on-boards", "on checkerboard captures (little texture)", argv=["calibrate-scene", "cb", *CS[2:]],
       setup=use("cb"), expect="either", check=calib_close("o.json", "cb/truth.json", 15.0, 2.0, 0.5))
    cs("two-frames", "a 2-frame capture (fewer than 3)", argv=["calibrate-scene", "sc", *CS[2:]], setup=use("sc"))
    cs("out-dir", "-o an existing folder", argv=[*CS[:-3], "-o", "o.json", "--quiet", "--max-frames", "3"],
       setup=mkdirs("o.json"))
    cs("out-is-image", "-o an input image", argv=[*CS[:-3], "-o", "sc6/000/r00_c00.png", "--quiet", "--max-frames",
                                                   "3"])
    cs("black", "every image black", setup=images("sc6", lambda im, f, v: im * 0))
    cs("noise", "every image independent noise", ["--max-frames", "3"],
       setup=images("sc6", lambda im, f, v: np.random.default_rng(f * 4 + v).integers(0, 256, im.shape, np.uint8)))
    cs("colour", "every image colour", ["--max-frames", "3"],
       setup=images("sc6", lambda im, f, v: cv2.cvtColor(im, cv2.COLOR_GRAY2BGR)), expect="either", check=cs_good)

    # ------------------------------------------------------------------ rectify
    R = ["rectify", "cal.json", "cb", "-o", "rect", *Q]  # noqa: N806
    rect_ok = rectified_check("rect", 8)

    def rect(id_, desc, argv=None, setup=None, expect="error", **kw):
        cli(f"rectify-{id_}", "rectify", desc, argv or R, chain(use("cb", "cal.json"), setup), expect, **kw)

    rect("valid", "valid", expect="ok", check=rect_ok)
    rect("crop-full", "--crop full", [*R, "--crop", "full"], expect="ok", check=rect_ok)
    rect("crop-bogus", "--crop bogus", [*R, "--crop", "bogus"])
    rect("out-nonempty", "-o an existing non-empty folder", setup=put("rect/keep.txt", "keep"))
    rect("out-empty-dir", "-o an existing empty folder", setup=mkdirs("rect"), expect="ok", check=rect_ok)
    rect("out-inside", "-o inside the input", [*R[:3], "-o", "cb/rect", *Q])
    rect("out-is-calib", "-o is the calibration file", [*R[:3], "-o", "cal.json", *Q])
    rect("out-symlink-dir", "-o a symlink to an empty folder", [*R[:3], "-o", "lrect", *Q],
         setup=chain(mkdirs("real"), symlink("lrect", "real")), expect="either", check=rectified_check("lrect", 8))
    rect("out-devnull", "-o a null device", [*R[:3], "-o", "dev_null", *Q], setup=device("dev_null"))
    rect("out-fifo", "-o a FIFO", setup=fifo("rect"))
    rect("out-nested", "-o in missing parents a/b/c", [*R[:3], "-o", "a/b/c", *Q], expect="either",
         check=rectified_check("a/b/c", 8))
    rect("out-is-capture", "-o is the input capture", [*R[:3], "-o", "cb", *Q])
    rect("calib-missing", "calibration file missing", ["rectify", "nope.json", "cb", "-o", "rect", *Q])
    rect("calib-12", "a 1x2 calibration on a 2x2 capture", ["rectify", "t12.json", "cb", "-o", "rect", *Q],
         setup=use("t12.json=cb12/truth.json"))
    rect("calib-size", "a 400x300 calibration on 320x240 images", ["rectify", "ts.json", "cb", "-o", "rect", *Q],
         setup=use("ts.json=other_size/truth.json"))
    rect("capture-empty", "an empty capture folder", ["rectify", "cal.json", "e", "-o", "rect", *Q], setup=mkdirs("e"))
    rect("late-bad-size", "frame 5 view 2 resized (fails mid-run)",
         setup=images("cb", lambda im, f, v: cv2.resize(im, (300, 200)), frames=(5,), views=(2,)))
    rect("late-truncated", "frame 6 view 1 truncated (fails mid-run)", setup=file_op("cb", _truncate, (6,), (1,)))
    rect("late-fifo", "frame 6 view 1 is a FIFO", setup=file_op("cb", _to_fifo, (6,), (1,)))
    rect("colour", "colour images", setup=images("cb", lambda im, f, v: cv2.cvtColor(im, cv2.COLOR_GRAY2BGR)),
         expect="either", check=rect_ok)
    rect("uint16", "16-bit images", setup=images("cb", lambda im, f, v: im.astype(np.uint16) * 257), expect="either",
         check=rect_ok)
    rect("jobs0", "--jobs 0", ["rectify", "cal.json", "cb", "-o", "rect", "--jobs", "0"])
    rect("jobs2", "--jobs 2 (valid)", ["rectify", "cal.json", "cb", "-o", "rect", "--jobs", "2", "--quiet"],
         expect="ok", check=rect_ok)
    rect("save-valid", "--save r.rrd (valid)", [*R, "--save", "r.rrd"], expect="ok",
         check=all_of(rect_ok, exists_check("r.rrd")))
    rect("save-is-output", "--save is the -o folder", [*R, "--save", "rect"])
    rect("save-in-output", "--save inside the -o folder", [*R, "--save", "rect/r.rrd"])
    rect("save-is-calib", "--save is the calibration", [*R, "--save", "cal.json"])
    rect("mosaic", "a mosaic capture", ["rectify", "cal.json", "cb_mosaic", "-o", "rect", *Q], setup=use("cb_mosaic"),
         expect="ok", check=lambda c, d, r: (len(list((d / "rect").glob("*.png"))) == 8, "8 mosaics written"))
    rect("k1-50-api", "a calibration with k1 = 50 (fold-over)", ["rectify", "c.json", "cb", "-o", "rect", *Q],
         setup=json_variant("c.json", S("views", 2, "distortion", "k1", 50.0)))

    # ------------------------------------------------------------------ refine
    F = ["refine", "sc/original.json", "sc", "-o", "r.json", "--quiet"]  # noqa: N806
    ref_ok = not_worse("r.json", "sc/original.json", "sc/truth.json")

    def refine(id_, desc, extra=(), setup=None, expect="error", argv=None, **kw):
        cli(f"refine-{id_}", "refine", desc, argv or [*F, *extra], chain(use("sc"), setup), expect, **kw)

    refine("valid", "valid (shaken 2x2, 2 frames)", expect="ok", check=ref_ok)
    refine("overwrite", "-o is the input calibration, with --overwrite", argv=[*F[:3], "-o", "sc/original.json",
                                                                              "--overwrite", "--quiet"],
           expect="ok", mutable=(r"original\.json$",),
           check=lambda c, d, r: (errors_vs(d / "sc/original.json", d / "sc/truth.json")["rms_rotation_deg"] < 0.1,
                                  "replaced in place by a better calibration"))
    refine("overwrite-missing", "-o is the input calibration without --overwrite",
           argv=[*F[:3], "-o", "sc/original.json", "--quiet"])
    refine("out-image", "-o is an input image", argv=[*F[:3], "-o", "sc/000/r00_c00.png", "--quiet"])
    refine("out-dir", "-o is a folder", argv=[*F[:3], "-o", "sc", "--quiet"])
    refine("out-fifo", "-o is a FIFO", setup=fifo("r.json"))
    refine("out-symlink-calib", "-o a symlink to the input calibration", argv=[*F[:3], "-o", "l.json", "--quiet"],
           setup=symlink("l.json", "sc/original.json"))
    refine("out-hardlink-calib", "-o a hard link to the input calibration", argv=[*F[:3], "-o", "h.json", "--quiet"],
           setup=lambda d: os.link(d / "sc/original.json", d / "h.json"))
    for st in ("bogus", "", "clean", "clean,points", "points", "paper", "intrinsics,clean", "all,all,all",
               "points,,poses"):
        valid = st in ("points", "paper", "intrinsics,clean", "all,all,all", "points,,poses")
        refine(f"stages-{re.sub(r'[^a-z]', '_', st) or 'empty'}", f"--stages {st!r}", ["--stages", st],
               expect="either" if valid else "error", check=ref_ok)
    for rb in ("bogus", "huber:-1", "huber:nan", "cauchy:0.5", "tukey:1e-300", "huber:1e300"):
        refine(f"robust-{re.sub(r'[^0-9a-z]', '_', rb)}", f"--robust {rb}", ["--robust", rb],
               expect="either" if rb in ("cauchy:0.5", "tukey:1e-300", "huber:1e300") else "error", check=ref_ok)
    refine("trifilter-bogus", "--triangulation-filter bogus", ["--triangulation-filter", "bogus"])
    refine("trifilter-none", "--triangulation-filter none", ["--triangulation-filter", "none"], expect="ok",
           check=ref_ok)
    for mf in ("0", "-1", "1", "1000"):
        refine(f"maxframes-{mf.replace('-', 'm')}", f"--max-frames {mf}", ["--max-frames", mf],
               expect="either" if mf in ("1", "1000") else "error", check=ref_ok)
    for tr in ("0", "-1", "nan", "1e-9", "1e9"):
        refine(f"targetrms-{tr.replace('-', 'm').replace('.', '_')}", f"--target-rms {tr}", ["--target-rms", tr],
               expect="either" if tr in ("1e-9", "1e9") else "error", check=ref_ok)
    for dr in ("bogus=1", "roll_deg=-1", "roll_deg=nan", "roll_deg=1e300", "roll_deg=", "roll_deg", "roll_deg=1e-300",
               "position_mm=1,position_mm=2", ",", "roll_deg=inf"):
        valid = dr in ("roll_deg=1e300", "roll_deg=1e-300", "position_mm=1,position_mm=2")
        refine(f"drift-{re.sub(r'[^0-9a-z]', '_', dr)}", f"--drift {dr!r}", ["--drift", dr],
               expect="either" if valid else "error", check=ref_ok)
    refine("free", "--free", ["--free"], expect="ok", check=ref_ok)
    for fo in ("-1", "1", "0", "2", "100", "abc"):
        refine(f"folds-{fo.replace('-', 'm')}", f"--folds {fo}", ["--folds", fo],
               expect="either" if fo in ("0", "2", "100") else "error", check=ref_ok)
    for sg in ("0", "-1", "nan", "1e300"):
        refine(f"significance-{sg.replace('-', 'm')}", f"--significance {sg}", ["--significance", sg],
               expect="either" if sg == "1e300" else "error",
               check=lambda c, d, r: (errors_vs(d / "r.json", d / "sc/original.json")["rms_rotation_deg"] == 0,
                                      "nothing applied at 1e300 sigma"))
    for tp in ("-1", "nan", "inf", "0", "1e9"):
        refine(f"tolerance-{tp.replace('-', 'm')}", f"--tolerance-px {tp}", ["--tolerance-px", tp],
               expect="either" if tp in ("0", "1e9") else "error", check=ref_ok)
    for rf in ("3", "4", "-1"):
        refine(f"reference-{rf.replace('-', 'm')}", f"--reference {rf}", ["--reference", rf],
               expect="either" if rf == "3" else "error", check=loads_check("r.json"))
    refine("layout-mosaic", "--layout mosaic on a folders capture", ["--layout", "mosaic"])
    refine("other-camera", "a calibration of another camera of the same model (seed 7 capture)",
           argv=["refine", "sc/original.json", "other_seed", "-o", "r.json", "--quiet"], setup=use("other_seed"),
           expect="ok", check=not_worse("r.json", "sc/original.json", "other_seed/truth.json", 0.02, 0.5))
    refine("other-size", "a calibration for 400x300 images", argv=["refine", "ts.json", "sc", "-o", "r.json"],
           setup=use("ts.json=other_size/truth.json"))
    refine("other-grid", "a 1x2 calibration on a 2x2 capture", argv=["refine", "t12.json", "sc", "-o", "r.json"],
           setup=use("t12.json=cb12/truth.json"))
    refine("cap-empty", "an empty capture folder", argv=["refine", "sc/original.json", "e", "-o", "r.json"],
           setup=mkdirs("e"))
    refine("cap-one-frame", "a 1-frame capture", setup=remove("sc/001"), expect="ok", check=ref_ok)
    refine("cap-dup", "frames duplicated (4 frames)", setup=lambda d: [shutil.copytree(d / f"sc/{i:03d}",
                                                                                       d / f"sc/{i + 2:03d}")
                                                                       for i in range(2)], expect="ok", check=ref_ok)
    refine("cap-colour", "colour images", setup=images("sc", lambda im, f, v: cv2.cvtColor(im, cv2.COLOR_GRAY2BGR)),
           expect="either", check=ref_ok)
    refine("cap-uint16", "16-bit images", setup=images("sc", lambda im, f, v: im.astype(np.uint16) * 257),
           expect="either", check=ref_ok)
    refine("cap-black", "every image black", setup=images("sc", lambda im, f, v: im * 0))
    refine("cap-noise", "every image independent noise",
           setup=images("sc", lambda im, f, v: np.random.default_rng(f * 4 + v).integers(0, 256, im.shape, np.uint8)),
           expect="either", check=ref_ok)
    refine("cap-same-view", "every view shows the reference view's image (no parallax)",
           setup=images("sc", lambda im, f, v: cv2.imread(str(DATA / f"sc/{f:03d}/r00_c00.png"), 0), views=(1, 2, 3)),
           expect="either", check=loads_check("r.json"))
    refine("cap-swapped", "views r00_c01 and r01_c00 swapped in every frame",
           setup=lambda d: [(os.rename(d / f"sc/{i:03d}/r00_c01.png", d / "t.png"),
                             os.rename(d / f"sc/{i:03d}/r01_c00.png", d / f"sc/{i:03d}/r00_c01.png"),
                             os.rename(d / "t.png", d / f"sc/{i:03d}/r01_c00.png")) for i in range(2)],
           expect="either", check=loads_check("r.json"))
    refine("cap-resized", "frame 1 view 3 resized", setup=images("sc", lambda im, f, v: cv2.resize(im, (300, 200)),
                                                                 frames=(1,), views=(3,)))
    refine("cap-truncated", "frame 1 view 3 truncated", setup=file_op("sc", _truncate, (1,), (3,)))
    refine("cap-fifo", "frame 1 view 3 is a FIFO", setup=file_op("sc", _to_fifo, (1,), (3,)))
    refine("json", "--json", ["--json"], expect="ok", check=all_of(strict_json_stdout(), ref_ok))
    refine("save-valid", "--save r.rrd", ["--save", "r.rrd"], expect="ok", check=all_of(ref_ok, exists_check("r.rrd")))
    refine("save-is-output", "--save is -o", ["--save", "r.json"])
    refine("save-is-calib", "--save is the input calibration", ["--save", "sc/original.json"])

    # ------------------------------------------------------------------ check
    K = ["check", "sc/original.json", "sc"]  # noqa: N806

    def chk(id_, desc, extra=(), setup=None, expect="error", argv=None, **kw):
        kw.setdefault("ok_codes", (0, 3))
        cli(f"check-{id_}", "check", desc, argv or [*K, *extra], chain(use("sc"), setup), expect, **kw)

    chk("drifted", "valid: a shaken rig (exit 3 expected)", expect="ok", check=rc_is(3, "the rig was shaken"))
    chk("still", "valid: an unshaken rig (exit 0 expected)", argv=["check", "sc_still/truth.json", "sc_still"],
        setup=use("sc_still"), expect="ok", check=rc_is(0, "the rig did not move"))
    chk("other-camera", "another camera's capture (seed 7)", argv=["check", "sc/original.json", "other_seed"],
        setup=use("other_seed"), expect="ok", check=rc_is(3, "another camera"))
    for tp in ("-1", "nan", "inf", "0"):
        chk(f"tolerance-{tp.replace('-', 'm')}", f"--tolerance-px {tp}", ["--tolerance-px", tp],
            expect="either" if tp == "0" else "error", check=rc_is(3, "the rig was shaken"))
    for dp in ("", "abc", "-1", "0", "nan", "1e308", "1,,2", "inf"):
        chk(f"depths-{re.sub(r'[^0-9a-z]', '_', dp) or 'empty'}", f"--depths {dp!r}", ["--depths", dp, "--json"],
            expect="either" if dp in ("1e308", "1,,2") else "error", check=strict_json_stdout())
    for mf in ("0", "1", "1000"):
        chk(f"maxframes-{mf}", f"--max-frames {mf}", ["--max-frames", mf], expect="either" if mf != "0" else "error",
            check=rc_is(3, "the rig was shaken"))
    chk("drift-bogus", "--drift bogus", ["--drift", "bogus"])
    chk("json", "--json", ["--json"], expect="ok", check=all_of(strict_json_stdout(), rc_is(3, "shaken")))
    chk("other-size", "a 400x300 calibration", argv=["check", "ts.json", "sc"], setup=use("ts.json=other_size/truth.json"))
    chk("other-grid", "a 1x2 calibration", argv=["check", "t12.json", "sc"], setup=use("t12.json=cb12/truth.json"))
    chk("cap-empty", "an empty capture", argv=["check", "sc/original.json", "e"], setup=mkdirs("e"))
    chk("cap-black", "black images", setup=images("sc", lambda im, f, v: im * 0))
    chk("cap-colour", "colour images", setup=images("sc", lambda im, f, v: cv2.cvtColor(im, cv2.COLOR_GRAY2BGR)),
        expect="either", check=rc_is(3, "the rig was shaken"))
    chk("cap-noise", "independent noise images",
        setup=images("sc", lambda im, f, v: np.random.default_rng(f * 4 + v).integers(0, 256, im.shape, np.uint8)),
        expect="either", check=lambda c, d, r: (r.rc == 0, f"exit {r.rc} (3 would call noise a drift)"))
    chk("cap-fifo", "frame 0 view 1 is a FIFO", setup=file_op("sc", _to_fifo, (0,), (1,)))
    chk("cap-file", "INPUT is a file", argv=["check", "sc/original.json", "sc/truth.json"])

    # ------------------------------------------------------------------ fleet
    FL = ["fleet", "manifest.csv", "-o", "res.csv", "--jobs", "1", "--quiet"]  # noqa: N806

    def fleet(id_, desc, manifest=None, argv=None, setup=None, expect="error", **kw):
        kw.setdefault("allow_new", ())
        cli(f"fleet-{id_}", "fleet", desc, argv or FL,
            chain(use("sc"), put("manifest.csv", manifest) if manifest is not None else use("manifest.csv"), setup),
            expect, **kw)

    hdr = "camera,calibration,capture"
    fleet("valid", "valid manifest (one shaken camera)", expect="ok",
          check=csv_rows_check("res.csv", 1, "verdict", "DRIFTED"))
    fleet("missing", "manifest missing", argv=["fleet", "nope.csv", "-o", "res.csv"])
    fleet("empty", "manifest empty", "")
    fleet("header-only", "manifest with only its header", hdr + "\n", expect="either",
          check=lambda c, d, r: (True, "no cameras"))
    fleet("wrong-columns", "manifest with other columns", "name,calib,dir\ncam1,sc/original.json,sc\n")
    fleet("binary", "manifest binary garbage", bytes(range(256)) * 8)
    fleet("utf16", "manifest encoded UTF-16", (hdr + "\ncam1,sc/original.json,sc\n").encode("utf-16"))
    fleet("bom", "manifest with a UTF-8 BOM (as Excel saves CSV)", b"\xef\xbb\xbf" + f"{hdr}\ncam1,sc/original.json,sc\n".encode(),
          expect="either", check=csv_rows_check("res.csv", 1, "verdict", "DRIFTED"))
    fleet("crlf", "manifest with CRLF line ends", f"{hdr}\r\ncam1,sc/original.json,sc\r\n", expect="ok",
          check=csv_rows_check("res.csv", 1, "verdict", "DRIFTED"))
    fleet("calib-missing", "a row whose calibration does not exist (ERROR row expected)",
          f"{hdr}\ncam1,nope.json,sc\n", expect="ok", check=csv_rows_check("res.csv", 1, "verdict", "ERROR"))
    fleet("capture-missing", "a row whose capture does not exist (ERROR row expected)",
          f"{hdr}\ncam1,sc/original.json,nope\n", expect="ok", check=csv_rows_check("res.csv", 1, "verdict", "ERROR"))
    fleet("calib-fifo", "a row whose calibration is a FIFO", f"{hdr}\ncam1,f.json,sc\n", setup=fifo("f.json"),
          expect="either", check=csv_rows_check("res.csv", 1, "verdict", "ERROR"))
    for col, val in (("max_frames", "-1"), ("max_frames", "abc"), ("max_frames", "0"), ("max_px", "nan"),
                     ("max_px", "-1"), ("tolerance_px", "-1"), ("tolerance_px", "inf"), ("layout", "bogus")):
        fleet(f"{col}-{val.replace('-', 'm')}", f"manifest {col}={val}", f"{hdr},{col}\ncam1,sc/original.json,sc,{val}\n",
              expect="either", check=csv_rows_check("res.csv", 1, "verdict", "ERROR"))
    fleet("repeated", "a camera named twice", f"{hdr}\ncam1,sc/original.json,sc\ncam1,sc/original.json,sc\n")
    fleet("empty-name", "an empty camera name", f"{hdr}\n,sc/original.json,sc\n")
    fleet("escape", "a calibration path climbing out of the manifest's folder", f"{hdr}\ncam1,../../data/cal.json,sc\n",
          expect="either", check=csv_rows_check("res.csv", 1, "verdict", "ERROR"))
    fleet("two-same", "two cameras sharing one calibration and capture",
          f"{hdr}\ncam1,sc/original.json,sc\ncam2,sc/original.json,sc\n", expect="ok",
          check=csv_rows_check("res.csv", 2, "verdict", "DRIFTED"))
    fleet("short-row", "a row with too few fields", f"{hdr}\ncam1,sc/original.json\n")
    fleet("out-is-manifest", "-o is the manifest", argv=["fleet", "manifest.csv", "-o", "manifest.csv"])
    fleet("out-dir", "-o is a folder", argv=["fleet", "manifest.csv", "-o", "sc"])
    fleet("out-missing-dir", "-o in a missing folder", argv=["fleet", "manifest.csv", "-o", "nope/res.csv"])
    fleet("out-garbage", "-o an existing file of garbage (resumed?)", setup=put("res.csv", bytes(range(256)) * 4))
    fleet("out-other-csv", "-o an existing CSV with other columns", setup=put("res.csv", "a,b\n1,2\n"))
    fleet("out-capture-calib", "-o is the capture's calibration file", argv=["fleet", "manifest.csv", "-o",
                                                                          "sc/original.json"])
    fleet("executor-bogus", "--executor bogus", argv=[*FL, "--executor", "bogus"])
    fleet("executor-dask-dead", "--executor dask://127.0.0.1:1 (nothing listens)",
          argv=[*FL, "--executor", "dask://127.0.0.1:1"])
    fleet("jobs0", "--jobs 0", argv=["fleet", "manifest.csv", "-o", "res.csv", "--jobs", "0"])
    fleet("jobs16", "--jobs 16 for one camera", argv=["fleet", "manifest.csv", "-o", "res.csv", "--jobs", "16",
                                                      "--quiet"],
          expect="ok", check=csv_rows_check("res.csv", 1, "verdict", "DRIFTED"))
    fleet("manifest-fifo", "the manifest is a FIFO nobody writes", setup=fifo("manifest.csv"))
    for free_kib in (12, 4):  # 12 KiB: the version fits, the results do not; 4 KiB: not even the version
        setup, teardown = full_fs("full", free_kib, {"sc/original.json": "sc/original.json",
                                                     "manifest.csv": "text:camera,calibration,capture\n"
                                                                     "cam1,sc/original.json,CASE/sc\n"})
        fleet(f"full-disk-{free_kib}k", f"manifest, calibration and results on a full file system ({free_kib} KiB free)",
              argv=["fleet", "full/manifest.csv", "-o", "full/res.csv", "--jobs", "1", "--quiet"], setup=setup,
              teardown=teardown, expect="either", check=csv_rows_check("full/res.csv", 1))
    fleet("lock-present", "a lock file beside the results (left by a crashed run)", setup=put(".res.csv.lock", ""),
          expect="either", mutable=(r"\.lock$",), check=csv_rows_check("res.csv", 1, "verdict", "DRIFTED"))

    # ------------------------------------------------------------------ synth
    SY = ["synth", "checkerboard", "out", "--scene", "small-2x2", "--frames", "2", *Q]  # noqa: N806
    synth_ok = exists_check("out/truth.json", "out/000/r00_c00.png", "out/001/r01_c01.png")

    def syn(id_, desc, extra=(), setup=None, expect="error", argv=None, **kw):
        cli(f"synth-{id_}", "synth", desc, argv or [*SY, *extra], setup, expect, **kw)

    syn("valid", "valid", expect="ok", check=synth_ok)
    syn("out-user", "OUT an existing folder with a user's files", setup=put("out/thesis.txt", "years of work"))
    syn("overwrite-user", "--overwrite on a user's folder", ["--overwrite"], setup=put("out/thesis.txt", "years"))
    syn("overwrite-synth", "--overwrite on an earlier synthetic set", ["--overwrite"],
        setup=lambda d: subprocess.run([str(LFG), *SY], cwd=d, capture_output=True), expect="ok",
        mutable=(r"^out/",), check=synth_ok)
    syn("overwrite-synth-userfile", "--overwrite on an earlier synthetic set that also holds a user's file",
        ["--overwrite"], setup=chain(lambda d: subprocess.run([str(LFG), *SY], cwd=d, capture_output=True),
                                     put("out/thesis.txt", "years of work")),
        expect="either", mutable=(r"^out/(?!thesis\.txt)",), check=synth_ok)
    syn("out-file", "OUT is a file", setup=put("out", "x"))
    syn("out-symlink-user-overwrite", "OUT a symlink to a user's folder, --overwrite", ["--overwrite"],
        setup=chain(put("user/thesis.txt", "years"), symlink("out", "user")))
    syn("out-devnull", "OUT a null device", argv=["synth", "checkerboard", "dev_null", "--scene", "small-2x2", *Q],
        setup=device("dev_null"))
    syn("out-in-capture", "OUT inside another capture", argv=["synth", "checkerboard", "cb/extra", "--scene",
                                                              "small-2x2", "--frames", "1", *Q],
        setup=use("cb"), expect="either", check=exists_check("cb/extra/truth.json"))
    for fr in ("0", "-1"):
        syn(f"frames-{fr.replace('-', 'm')}", f"--frames {fr}", argv=[*SY[:5], "--frames", fr, *Q])
    for isz in ("1x1", "0x0", "16385x10", "8x8", "abc"):
        syn(f"imagesize-{isz}", f"--image-size {isz}", ["--image-size", isz],
            expect="either" if isz in ("1x1", "8x8") else "error", check=synth_ok)
    for g in ("0x0", "1x1", "12x12"):
        syn(f"grid-{g}", f"--grid {g}", ["--grid", g, "--image-size", "64x48"] if g == "12x12" else ["--grid", g],
            expect="either" if g != "0x0" else "error",
            check=exists_check("out/truth.json"))
    for b in ("1x1", "2x2", "100x100", "7x5x1"):
        syn(f"board-{b}", f"--board {b}", ["--board", b], expect="either" if b in ("2x2", "100x100") else "error",
            check=synth_ok)
    for sq in ("0", "-1", "1e6", "nan"):
        syn(f"square-{sq.replace('-', 'm')}", f"--square-mm {sq}", ["--square-mm", sq],
            expect="either" if sq == "1e6" else "error", check=synth_ok)
    for rf in ("99", "4", "3"):
        syn(f"reference-{rf}", f"--reference {rf}", ["--reference", rf], expect="ok" if rf == "3" else "error",
            check=synth_ok)
    for sd in ("-1", str(2**70)):
        syn(f"seed-{sd[:6].replace('-', 'm')}", f"--seed {sd}", ["--seed", sd], expect="either", check=synth_ok)
    syn("scene-bogus", "--scene bogus", argv=["synth", "checkerboard", "out", "--scene", "bogus", *Q])
    syn("jobs0", "--jobs 0", argv=["synth", "checkerboard", "out", "--scene", "small-2x2", "--jobs", "0"])
    SS = ["synth", "scene", "out", "--scene", "small-2x2", "--frames", "1", *Q]  # noqa: N806
    for flag, val, exp in (("--shake-rot-deg", "-1", "either"), ("--shake-rot-deg", "nan", "error"),
                           ("--shake-rot-deg", "1e6", "either"), ("--shake-trans-mm", "1e9", "either"),
                           ("--shake-trans-mm", "inf", "error"), ("--shake-axis", "bogus", "error"),
                           ("--layout", "hci", "error"), ("--keyboard", None, "ok"), ("--layout", "mosaic", "ok")):
        syn(f"scene{flag.replace('-', '_')}-{(val or 'on').replace('-', 'm')}", f"synth scene {flag} {val or ''}",
            argv=[*SS, flag] + ([val] if val else []), expect=exp, check=exists_check("out/truth.json"))

    # ------------------------------------------------------------------ study
    SH = ["study", "shake", "--scene", "small-2x2", "--trials", "1", "--rot-deg", "0.5", "--trans-mm", "1",  # noqa: N806
          "--stages", "default", "--robust", "none", "--jobs", "1", "-o", "s.csv", "--quiet"]

    def study(id_, desc, argv, setup=None, expect="error", **kw):
        cli(f"study-{id_}", "study", desc, argv, setup, expect, **kw)

    def sh_with(flag, val):
        a = list(SH)
        a[a.index(flag) + 1] = val
        return a

    study("shake-valid", "study shake, 1 trial (valid)", SH, expect="ok", check=csv_rows_check("s.csv", 1))
    for flag, val in (("--trials", "0"), ("--trials", "-1"), ("--rot-deg", "a"), ("--rot-deg", ""),
                      ("--rot-deg", "nan"), ("--rot-deg", "-1"), ("--stages", "bogus"), ("--robust", "bogus"),
                      ("--scene", "bogus"), ("--jobs", "0")):
        study(f"shake{flag.replace('-', '_')}-{re.sub(r'[^0-9a-z]', '_', val) or 'empty'}", f"study shake {flag} {val!r}",
              sh_with(flag, val))
    study("shake-mismatch", "--rot-deg 0,1 with --trans-mm 1 (broadcast is acceptable)", sh_with("--rot-deg", "0,1"),
          expect="either", check=csv_rows_check("s.csv", 2))
    study("shake-frames0", "--frames 0", [*SH, "--frames", "0"])
    study("shake-out-dir", "-o a folder", sh_with("-o", "sub"), setup=mkdirs("sub"))
    study("shake-out-garbage", "-o an existing file of garbage (resume)", SH, setup=put("s.csv", bytes(range(256)) * 4))
    study("shake-out-othercsv", "-o an existing CSV of another study", SH,
          setup=put("s.csv", "scene,method,sigma_px,frames,seed\nsmall-2x2,joint,0.1,5,0\n"))
    study("shake-out-devnull", "-o a null device (a private node standing for /dev/null)", sh_with("-o", "dev_null"),
          setup=device("dev_null"))

    study("shake-out-png", "-o s.png (the figure's own name)", sh_with("-o", "s.png"))
    study("shake-out-missing", "-o in a missing folder", sh_with("-o", "nope/s.csv"))
    study("shake-executor-bogus", "--executor bogus", [*SH, "--executor", "bogus"])
    study("shake-executor-dead", "--executor dask://127.0.0.1:1", [*SH, "--executor", "dask://127.0.0.1:1"])
    study("shake-save-is-out", "--save is the CSV", [*SH, "--save", "s.csv"])
    study("shake-save-valid", "--save s.rrd", [*SH, "--save", "s.rrd"], expect="ok",
          check=all_of(csv_rows_check("s.csv", 1), exists_check("s.rrd")))
    CST = ["study", "calibration", "--scene", "small-2x2", "--trials", "1", "--frames", "5", "--sigma-px", "0.1",  # noqa: N806
           "--jobs", "1", "-o", "c.csv", "--quiet"]

    def cst_with(flag, val):
        a = list(CST)
        a[a.index(flag) + 1] = val
        return a

    study("calib-valid", "study calibration (valid)", CST, expect="ok", check=csv_rows_check("c.csv", 1))
    for flag, val, exp in (("--frames", "0", "error"), ("--frames", "1", "either"), ("--frames", "2", "either"),
                           ("--sigma-px", "-1", "error"), ("--sigma-px", "nan", "error"), ("--sigma-px", "0", "either"),
                           ("--sigma-px", "1e6", "either"), ("--trials", "0", "error")):
        study(f"calib{flag.replace('-', '_')}-{val.replace('-', 'm')}", f"study calibration {flag} {val}",
              cst_with(flag, val), expect=exp, check=csv_rows_check("c.csv", 1))
    study("calib-out-devnull", "study calibration -o a null device", cst_with("-o", "dev_null"),
          setup=device("dev_null"))
    study("calib-out-shakecsv", "study calibration -o an existing shake-study CSV", CST,
          setup=put("c.csv", "scene,stages,robust,level,rot_deg,trans_mm,seed\nsmall-2x2,default,none,0,0.5,1,0\n"))

    # ------------------------------------------------------------------ depth-error
    DE = ["depth-error", "--focal-px", "850", "--baseline-m", "0.018", "--error-px", "0.246", "--json"]  # noqa: N806

    def de_with(flag, *vals):
        a = list(DE)
        i = a.index(flag) if flag in a else None
        if i is None:
            return [*a, flag, *vals]
        return [*a[:i + 1], *vals, *a[i + 2:]]

    de_ok = strict_json_stdout(depth_check)
    cli("depth-valid", "depth-error", "valid", DE, expect="ok", check=de_ok)
    for flag, vals, exp in (("--focal-px", ("0",), "error"), ("--focal-px", ("-1",), "error"),
                            ("--focal-px", ("nan",), "error"), ("--focal-px", ("inf",), "error"),
                            ("--baseline-m", ("0",), "error"), ("--baseline-m", ("-1",), "error"),
                            ("--baseline-m", ("1e-300",), "either"), ("--error-px", ("0",), "either"),
                            ("--error-px", ("-1",), "error"), ("--error-px", ("nan",), "error"),
                            ("--error-px", ("1e300",), "either"), ("--range-m", ("2", "0.5"), "either"),
                            ("--range-m", ("0", "1"), "error"), ("--range-m", ("-1", "1"), "error"),
                            ("--range-m", ("nan", "1"), "error"), ("--range-m", ("1", "1"), "either"),
                            ("--range-m", ("1e300", "1e301"), "either"), ("--steps", ("0",), "error"),
                            ("--steps", ("1",), "either"), ("--steps", ("-3",), "error")):
        cli(f"depth{flag.replace('-', '_')}-{'_'.join(vals).replace('-', 'm').replace('.', 'p')}", "depth-error",
            f"{flag} {' '.join(vals)}", de_with(flag, *vals), expect=exp, check=de_ok)
    cli("depth-steps-1e6", "depth-error", "--steps 1000000", [*DE[:-1], "--steps", "1000000"], expect="either",
        check=lambda c, d, r: (len(r.stdout) > 0, f"{len(r.stdout)} bytes printed"))
    cli("depth-plot-valid", "depth-error", "--plot de.png", [*DE, "--plot", "de.png"], expect="ok",
        check=all_of(de_ok, exists_check("de.png", "de.pdf")))
    cli("depth-plot-dir", "depth-error", "--plot an existing folder (figures beside it are acceptable)",
        [*DE, "--plot", "sub"], mkdirs("sub"), "either", check=exists_check("sub.png"))
    cli("depth-plot-missing", "depth-error", "--plot in a missing folder (created; acceptable)",
        [*DE, "--plot", "nope/de.png"], None, "either", check=exists_check("nope/de.png"))
    cli("depth-plot-ext", "depth-error", "--plot de.xyz (unknown format; de.png/de.pdf acceptable)",
        [*DE, "--plot", "de.xyz"], None, "either", check=exists_check("de.png"))
    cli("depth-plot-fifo", "depth-error", "--plot a FIFO", [*DE, "--plot", "de.png"], fifo("de.png"))
    cli("depth-plot-symlink", "depth-error", "--plot a symlink", [*DE, "--plot", "de.png"], symlink("de.png", "t.png"))
    cli("depth-plot-pdf-png", "depth-error", "--plot de.pdf (its PDF is itself)", [*DE, "--plot", "de.pdf"],
        expect="either", check=exists_check("de.pdf"))
    cli("depth-plot-devnull", "depth-error", "--plot a null device (figures beside it are acceptable)",
        [*DE, "--plot", "dev_null"], device("dev_null"), "either", check=exists_check("dev_null.png"))

    # ------------------------------------------------------------------ export / import
    for fmt, out in (("opencv-yaml", "x.yaml"), ("kalibr", "x.yaml"), ("colmap", "xcol"), ("json", "x.json")):
        cli(f"export-valid-{fmt}", "export", f"export --to {fmt} (valid)", ["export", "c.json", "--to", fmt, "-o", out],
            use("c.json=cal_rect.json"), "ok", check=roundtrip_check(out, fmt, "c.json"))
    EX = ["export", "cal.json", "--to"]  # noqa: N806
    cli("export-to-bogus", "export", "--to bogus", [*EX, "bogus", "-o", "x"], use("cal.json"))
    cli("export-out-input", "export", "-o is the input", [*EX, "json", "-o", "cal.json"], use("cal.json"))
    cli("export-colmap-file", "export", "colmap -o an existing file", [*EX, "colmap", "-o", "f"],
        chain(use("cal.json"), put("f", "x")))
    cli("export-colmap-nonempty", "export", "colmap -o an existing folder with a user's file", [*EX, "colmap", "-o", "m"],
        chain(use("cal.json"), put("m/notes.txt", "keep")), "either", check=exists_check("m/cameras.txt"))
    cli("export-colmap-perms", "export", "colmap -o a new folder: its permissions follow the umask",
        [*EX, "colmap", "-o", "m"], use("cal.json"), "ok",
        check=lambda c, d, r: ((d / "m").stat().st_mode & 0o777 == 0o755,
                               f"folder mode {oct((d / 'm').stat().st_mode & 0o777)} (umask 022 gives 0o755)"))
    cli("export-yaml-dir", "export", "opencv-yaml -o a folder", [*EX, "opencv-yaml", "-o", "sub"],
        chain(use("cal.json"), mkdirs("sub")))
    cli("export-fifo", "export", "-o a FIFO", [*EX, "json", "-o", "f.json"], chain(use("cal.json"), fifo("f.json")))
    cli("export-symlink", "export", "-o a symlink", [*EX, "json", "-o", "l.json"],
        chain(use("cal.json"), symlink("l.json", "t.json")))
    cli("export-missing-dir", "export", "-o in a missing folder", [*EX, "json", "-o", "nope/x.json"], use("cal.json"))
    IM = ["import"]  # noqa: N806

    def imp(id_, desc, src, fmt, setup, expect="error", extra=(), **kw):
        cli(f"import-{id_}", "import", desc, [*IM, src, "--from", fmt, *extra, "-o", "o.json"], setup, expect, **kw)

    imp("yaml-valid", "opencv-yaml (valid)", "cal.yaml", "opencv-yaml", use("cal.yaml", "cal.json"), "ok",
        check=loads_check("o.json"))
    imp("kalibr-valid", "kalibr --grid 2x2 (valid)", "camchain.yaml", "kalibr", use("camchain.yaml"), "ok",
        ("--grid", "2x2"), check=loads_check("o.json"))
    imp("colmap-valid", "colmap (valid)", "colmap", "colmap", use("colmap"), "ok", check=loads_check("o.json"))
    imp("json-valid", "json (valid)", "cal_export.json", "json", use("cal_export.json"), "ok",
        check=loads_check("o.json"))
    imp("middlebury-valid", "middlebury (valid)", "calib.txt", "middlebury", use("calib.txt"), "ok",
        check=loads_check("o.json"))
    imp("hci-valid", "hci (valid)", "parameters.cfg", "hci", use("parameters.cfg"), "ok", check=loads_check("o.json"))
    for fmt, name in (("opencv-yaml", "x.yaml"), ("kalibr", "x.yaml"), ("json", "x.json"), ("middlebury", "calib.txt"),
                      ("hci", "parameters.cfg")):
        extra = ("--grid", "2x2") if fmt == "kalibr" else ()
        imp(f"{fmt}-empty", f"{fmt}: empty file", name, fmt, put(name, ""), extra=extra)
        imp(f"{fmt}-binary", f"{fmt}: binary garbage", name, fmt, put(name, bytes(range(256)) * 8), extra=extra)
        imp(f"{fmt}-missing", f"{fmt}: file missing", name, fmt, None, extra=extra)
        imp(f"{fmt}-fifo", f"{fmt}: the file is a FIFO", name, fmt, fifo(name), extra=extra)
    imp("yaml-deep", "opencv-yaml nested 50000 deep", "x.yaml", "opencv-yaml",
        put("x.yaml", "%YAML:1.0\n---\nK_0: " + "[" * 50000 + "]" * 50000 + "\n"))
    imp("kalibr-deep", "kalibr nested 50000 deep", "x.yaml", "kalibr", put("x.yaml", "cam0: " + "[" * 50000 + "]" * 50000
                                                                           + "\n"), extra=("--grid", "1x1"))
    bomb = "a: &a [1,1,1,1,1,1,1,1,1]\n" + "".join(
        f"{chr(98 + i)}: &{chr(98 + i)} [{', '.join(['*' + chr(97 + i)] * 9)}]\n" for i in range(9))
    imp("kalibr-alias-bomb", "kalibr YAML alias bomb (billion laughs)", "x.yaml", "kalibr",
        put("x.yaml", bomb + "cam0:\n  intrinsics: *j\n"), extra=("--grid", "1x1"))
    imp("yaml-alias-bomb", "opencv-yaml alias bomb", "x.yaml", "opencv-yaml", put("x.yaml", "%YAML:1.0\n---\n" + bomb +
                                                                                   "K_0: *j\n"))
    imp("kalibr-python-tag", "kalibr YAML with a !!python/object tag", "x.yaml", "kalibr",
        put("x.yaml", "cam0: !!python/object/apply:os.system ['echo pwned > pwned.txt']\n"), extra=("--grid", "1x1"))
    imp("kalibr-nogrid", "kalibr without --grid", "camchain.yaml", "kalibr", use("camchain.yaml"))
    imp("kalibr-grid33", "kalibr --grid 3x3 for 4 cameras", "camchain.yaml", "kalibr", use("camchain.yaml"),
        extra=("--grid", "3x3"))
    imp("kalibr-grid14", "kalibr --grid 1x4 (4 cameras in a row)", "camchain.yaml", "kalibr", use("camchain.yaml"),
        "either", ("--grid", "1x4"), check=loads_check("o.json"))
    imp("colmap-empty", "colmap: empty folder", "colmap", "colmap", mkdirs("colmap"))
    imp("colmap-cameras-garbage", "colmap: cameras.txt garbage", "colmap", "colmap",
        chain(use("colmap"), put("colmap/cameras.txt", "1 OPENCV abc def\n")))
    imp("colmap-no-rigs", "colmap: rigs.txt missing", "colmap", "colmap", chain(use("colmap"), remove("colmap/rigs.txt")),
        "either", check=loads_check("o.json"))
    mb = "cam0=[300 0 160; 0 300 120; 0 0 1]\ncam1=[300 0 162; 0 300 120; 0 0 1]\nbaseline={b}\nwidth={w}\nheight=240\n"
    imp("mb-nobaseline", "middlebury: baseline missing", "calib.txt", "middlebury",
        put("calib.txt", "cam0=[300 0 160; 0 300 120; 0 0 1]\ncam1=[300 0 162; 0 300 120; 0 0 1]\nwidth=320\nheight=240\n"))
    imp("mb-negbaseline", "middlebury: baseline -10", "calib.txt", "middlebury", put("calib.txt", mb.format(b=-10, w=320)))
    imp("mb-nanbaseline", "middlebury: baseline nan", "calib.txt", "middlebury", put("calib.txt", mb.format(b="nan", w=320)))
    imp("mb-hugewidth", "middlebury: width 10^12", "calib.txt", "middlebury",
        put("calib.txt", mb.format(b=10, w=10**12)), "either", check=loads_check("o.json"))
    imp("mb-badmatrix", "middlebury: cam0 not a matrix", "calib.txt", "middlebury",
        put("calib.txt", mb.format(b=10, w=320).replace("[300 0 160; 0 300 120; 0 0 1]", "300")))
    imp("mb-folder", "middlebury: a folder without calib.txt", "sub", "middlebury", mkdirs("sub"))
    hci = ("[intrinsics]\nfocal_length_mm = {f}\nsensor_size_mm = 35\nimage_resolution_x_px = 320\n"
           "image_resolution_y_px = 240\n\n[extrinsics]\nnum_cams_x = {n}\nnum_cams_y = {n}\nbaseline_mm = 10\n")
    imp("hci-percent", "hci: a value with a '%' (INI interpolation)", "parameters.cfg", "hci",
        put("parameters.cfg", hci.format(f="100%", n=2)))
    imp("hci-huge", "hci: 100000 x 100000 cameras", "parameters.cfg", "hci", put("parameters.cfg", hci.format(f=100,
                                                                                                            n=100000)))
    imp("hci-zero", "hci: 0 x 0 cameras", "parameters.cfg", "hci", put("parameters.cfg", hci.format(f=100, n=0)))
    imp("hci-nosection", "hci: [extrinsics] missing", "parameters.cfg", "hci",
        put("parameters.cfg", hci.format(f=100, n=2).split("[extrinsics]")[0]))
    imp("hci-dupkey", "hci: a key given twice", "parameters.cfg", "hci",
        put("parameters.cfg", hci.format(f=100, n=2) + "num_cams_x = 3\n"))
    imp("ref99", "--grid 2x2 --reference 99", "cal_export.json", "json", use("cal_export.json"),
        extra=("--grid", "2x2", "--reference", "99"))
    imp("ref-nogrid", "--reference 1 without --grid", "cal_export.json", "json", use("cal_export.json"),
        extra=("--reference", "1"))
    imp("ref1", "--grid 2x2 --reference 1 (valid)", "cal_export.json", "json", use("cal_export.json"), "ok",
        ("--grid", "2x2", "--reference", "1"), check=loads_check("o.json"))
    cli("import-out-input", "import", "-o is the input", ["import", "cal_export.json", "--from", "json", "-o",
                                                        "cal_export.json"], use("cal_export.json"))
    cli("import-out-dir", "import", "-o a folder", ["import", "cal_export.json", "--from", "json", "-o", "sub"],
        chain(use("cal_export.json"), mkdirs("sub")))
    cli("import-from-bogus", "import", "--from bogus", ["import", "cal_export.json", "--from", "bogus", "-o", "o.json"],
        use("cal_export.json"))

    # ------------------------------------------------------------------ demo
    cli("demo-scene-bogus", "demo", "--scene bogus", ["demo", "--scene", "bogus", "--out", "d", "--quiet"])
    cli("demo-out-user", "demo", "--out a folder holding a user's file", ["demo", "--scene", "small-2x2", "--no-refine",
                                                                        "--jobs", "1", "--quiet", "--out", "d"],
        put("d/thesis.txt", "years of work"), "either", check=exists_check("d/calibration.json"))
    cli("demo-out-file", "demo", "--out is a file", ["demo", "--scene", "small-2x2", "--out", "f", "--quiet"],
        put("f", "keep"))
    cli("demo-valid", "demo", "small-2x2 --no-refine (valid)", ["demo", "--scene", "small-2x2", "--no-refine", "--jobs",
                                                               "1", "--quiet", "--out", "d"], expect="ok",
        check=calib_close("d/calibration.json", "d/small-2x2/truth.json"))

    # ------------------------------------------------------------------ Ctrl-C, kill -9, closed pipes
    def sig(id_, command, desc, argv, delay, setup, kind="sigint", **kw):
        add(Case(id_, command, desc, kind, [str(a) for a in argv], setup=setup, delay=delay, expect="error",
                 ok_codes=(0,), **kw))

    C40 = ["calibrate", "cb40", *CALARGS, "-o", "o.json", "--no-cache", "--quiet"]  # noqa: N806
    sig("sigint-calibrate-j1", "calibrate", "Ctrl-C during detection (--jobs 1)", [*C40, "--jobs", "1"], 2.0,
        use("cb40"), check=loads_check("o.json"))
    sig("sigint-calibrate-j2", "calibrate", "Ctrl-C during detection (--jobs 2)", [*C40, "--jobs", "2"], 2.0,
        use("cb40"), check=loads_check("o.json"))
    sig("sigint-calibrate-late", "calibrate", "Ctrl-C late (solve, --save, --plots)",
        [*C40, "--jobs", "2", "--save", "r.rrd", "--plots", "figs"], 6.0, use("cb40"), check=loads_check("o.json"))
    sig("sigint-rectify-j1", "rectify", "Ctrl-C mid-rectify (--jobs 1)", ["rectify", "cal.json", "cb40", "-o", "rect",
                                                                          "--jobs", "1", "--quiet"], 0.7,
        use("cb40", "cal.json"), check=rectified_check("rect", 40))
    sig("sigint-rectify-j2", "rectify", "Ctrl-C mid-rectify (--jobs 2)", ["rectify", "cal.json", "cb40", "-o", "rect",
                                                                          "--jobs", "2", "--quiet"], 0.7,
        use("cb40", "cal.json"), check=rectified_check("rect", 40))
    sig("sigint-refine", "refine", "Ctrl-C mid-refine", ["refine", "sc_big/original.json", "sc_big", "-o", "r.json",
                                                         "--quiet", "--save", "r.rrd"], 2.0, use("sc_big"),
        check=loads_check("r.json"))
    sig("sigint-calscene", "calibrate-scene", "Ctrl-C mid-solve", ["calibrate-scene", "sc6", "--grid", "2x2",
                                                                   "--pitch-mm", "10", "--focal-px", "300", "-o",
                                                                   "o.json", "--report-json", "rep.json", "--quiet"],
        4.0, use("sc6"), check=loads_check("o.json"))
    sig("sigint-study", "study", "Ctrl-C mid-study (3 trials)", [*sh_with("--trials", "3")], 2.5, None,
        check=csv_rows_check("s.csv", 3), allow_new=(r"^s\.csv$",))
    sig("sigint-synth-cb", "synth", "Ctrl-C mid-render (checkerboard, 40 frames)",
        ["synth", "checkerboard", "out", "--scene", "small-2x2", "--frames", "40", "--jobs", "1", "--quiet"], 0.5, None,
        check=exists_check("out/truth.json"))
    sig("sigint-synth-scene", "synth", "Ctrl-C mid-render (scene, 12 frames)",
        ["synth", "scene", "out", "--scene", "small-2x2", "--frames", "12", "--jobs", "2", "--quiet"], 1.5, None,
        check=exists_check("out/truth.json"))
    sig("sigint-fleet", "fleet", "Ctrl-C mid-fleet", ["fleet", "manifest.csv", "-o", "res.csv", "--jobs", "1", "--quiet"],
        0.8, use("sc", "manifest.csv"), check=csv_rows_check("res.csv", 1))
    sig("sigint-demo", "demo", "Ctrl-C mid-demo", ["demo", "--scene", "small-2x2", "--out", "d", "--jobs", "1",
                                                   "--quiet"], 4.0, None, check=exists_check("d/calibration.json"))
    sig("sigkill-calibrate-j2", "calibrate", "kill -9 of the parent mid-detection (--jobs 2): workers must die",
        [*C40, "--jobs", "2"], 2.0, use("cb40"), kind="sigkill")
    sig("sigkill-rectify-j2", "rectify", "kill -9 of the parent mid-rectify (--jobs 2)",
        ["rectify", "cal.json", "cb40", "-o", "rect", "--jobs", "2", "--quiet"], 0.7, use("cb40", "cal.json"),
        kind="sigkill", check=exists_check("rect/calibration.json", "rect/039/r01_c01.png"))
    # a caller bounding the run as Python's documentation shows: its pipes must end once the run is killed (the pool
    # workers and the fork server held them open, watching the killed parent with os.kill(pid, 0), which a zombie
    # passes)
    RECT40 = ["rectify", "cal.json", "cb40", "-o", "rect", "--jobs", "2", "--quiet"]  # noqa: N806
    SYNTH200 = ["synth", "checkerboard", "out", "--scene", "small-2x2", "--frames", "200", "--jobs", "2", "--quiet"]  # noqa: N806
    # (a run that finished its work within the second leaves its whole output: its check says whether it is whole)
    for command, argv, setup, whole in (
            ("calibrate", [*C40, "--jobs", "2"], use("cb40"), loads_check("o.json")),
            ("rectify", RECT40, use("cb40", "cal.json"), exists_check("rect/calibration.json", "rect/039/r01_c01.png")),
            ("synth", SYNTH200, None, exists_check("out/truth.json"))):
        sig(f"popen-kill-{command}-j2", command, "communicate(timeout=1) on pipes, kill(), communicate(): released?",
            argv, 1.0, setup, kind="popen-kill", check=whole)
    # Ctrl-C while the pool starts (the fork server loading its modules, workers unpickling their first task)
    for t in (0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0, 1.1, 1.2):
        sig(f"sigint-calibrate-j2-at{t:.1f}", "calibrate", f"Ctrl-C {t:g} s into calibrate --jobs 2",
            [*C40, "--jobs", "2"], t, use("cb40"), check=loads_check("o.json"))
        sig(f"sigint-rectify-j2-at{t:.1f}", "rectify", f"Ctrl-C {t:g} s into rectify --jobs 2", RECT40, t,
            use("cb40", "cal.json"), check=rectified_check("rect", 40))
    for t in (0.3, 0.6, 0.9, 1.2):  # the earlier set must be left as it was
        sig(f"sigint-synth-overwrite-at{t:.1f}", "synth", f"Ctrl-C {t:g} s into synth --overwrite of an earlier set",
            [*SYNTH200, "--overwrite"], t, use("out=cb40"),
            check=exists_check("out/truth.json"))

    def pipe_outputs(*names):
        def check(case, d, res):
            lf = _lf()
            for n in names:
                p = d / n
                if p.is_dir():
                    lf.Calibration.load(p / "calibration.json")
                elif p.exists():
                    lf.Calibration.load(p)
            return True, "outputs absent or complete"
        return check

    def pipe(id_, command, desc, argv, nbytes, setup, outputs=()):
        add(Case(id_, command, desc, "pipe", [str(a) for a in argv], setup=setup, delay=nbytes, expect="either",
                 ok_codes=(0,), check=pipe_outputs(*outputs)))

    pipe("pipe-calibrate", "calibrate", "--stdout | head -c 100", ["calibrate", "cb", *CALARGS, "-o", "o.json",
                                                                   "--stdout", *Q], 100, use("cb"), ("o.json",))
    pipe("pipe-refine", "refine", "--stdout | head -c 100", ["refine", "sc/original.json", "sc", "-o", "r.json",
                                                             "--stdout", "--quiet"], 100, use("sc"), ("r.json",))
    pipe("pipe-rectify", "rectify", "--stdout | head -c 100", ["rectify", "cal.json", "cb", "-o", "rect", "--stdout",
                                                               *Q], 100, use("cb", "cal.json"), ("rect",))
    pipe("pipe-study", "study", "study shake --stdout | head -c 100", [*SH, "--stdout"], 100, None)
    pipe("pipe-info", "info", "info | (reader gone before the output)", ["info", "cal.json"], 0, use("cal.json"))
    pipe("pipe-check-json", "check", "check --json | (reader gone)", ["check", "sc/original.json", "sc", "--json"], 0,
         use("sc"))
    pipe("pipe-depth-steps", "depth-error", "depth-error --steps 1000000 | head -c 100",
         ["depth-error", "--focal-px", "850", "--baseline-m", "0.018", "--error-px", "0.246", "--steps", "1000000"],
         100, None)
    pipe("pipe-evaluate", "evaluate", "evaluate | (reader gone)", ["evaluate", "cal.json", "--truth", "cb/truth.json"],
         0, use("cal.json", "cb"))
    add(Case("closed-stdout-calibrate", "calibrate", "--stdout with standard output closed (>&-)", "shell",
             code="LFG calibrate cb --grid 2x2 --board 7x5 --square-mm 15 -o o.json --stdout --jobs 1 --quiet >&-",
             setup=use("cb"), expect="either", check=pipe_outputs("o.json")))
    add(Case("closed-stdout-info", "info", "info with standard output closed (>&-)", "shell",
             code="LFG info cal.json >&-", setup=use("cal.json"), expect="either"))
    # closed standard streams (as under some service managers): the work is done, what is written is dropped
    CB_LONG = "calibrate cb --grid 2x2 --board 7x5 --square-mm 15 -o o.json --no-cache --jobs 2"  # noqa: N806
    SY_LONG = "synth checkerboard out --scene small-2x2 --frames 2 --jobs 2"  # noqa: N806
    for id_, command, code, setup, check in (
            ("closed-stderr-calibrate", "calibrate", f"LFG {CB_LONG} 2>&-", use("cb"), calib_close("o.json", "cb/truth.json")),
            ("closed-stderr-refine", "refine", "LFG refine sc/original.json sc -o r.json 2>&-", use("sc"),
             not_worse("r.json", "sc/original.json", "sc/truth.json")),
            ("closed-stderr-synth", "synth", f"LFG {SY_LONG} 2>&-", None, exists_check("out/truth.json")),
            ("closed-stdout-stderr-synth", "synth", f"LFG {SY_LONG} >&- 2>&-", None, exists_check("out/truth.json"))):
        closed = "standard output and error closed (>&- 2>&-)" if ">&-" in code.replace("2>&-", "") else \
            "standard error closed (2>&-)"
        add(Case(id_, command, f"{closed}, progress bars on", "shell", code=code, setup=setup, expect="ok", check=check))
    # the log's reader goes away: the run ends as a closed pipe ends a program (exit 141), leaving none of its outputs
    add(Case("pipe-verbose-calibrate", "calibrate", "-v calibrate 2>&1 | head -c 50", "shell",
             code=f"LFG -v {CB_LONG.replace('cb ', 'cb40 ', 1)} 2>&1 | head -c 50; exit ${{PIPESTATUS[0]}}",
             setup=use("cb40"), expect="ok", ok_codes=(141,),
             check=lambda case, d, res: (not (d / "o.json").exists(), "the run ended: o.json not written")))
    add(Case("closed-stderr-calibrate-bad", "calibrate", "a bad --board with standard error closed (2>&-)", "shell",
             code="LFG calibrate cb --grid 2x2 --board 6x4 --square-mm 15 -o o.json --jobs 1 --quiet 2>&-",
             setup=use("cb"), expect="error"))
    add(Case("full-disk-calibrate", "calibrate", "-o a 'full' device node (writes fail with ENOSPC)",
             "cli", ["calibrate", "cb", *CALARGS, "-o", "dev_full", *Q], setup=chain(use("cb"), device("dev_full", 1, 7)),
             expect="error"))
    # outputs that are device nodes, for every command with an output
    for id_, command, argv, extra_setup in (
            ("fleet-out-devnull", "fleet", ["fleet", "manifest.csv", "-o", "dev_null", "--jobs", "1", "--quiet"],
             use("sc", "manifest.csv")),
            ("calscene-out-devnull", "calibrate-scene", ["calibrate-scene", "sc6", "--grid", "2x2", "--pitch-mm", "10",
                                                         "--focal-px", "300", "--max-frames", "3", "-o", "dev_null",
                                                         "--quiet"], use("sc6")),
            ("calscene-report-devnull", "calibrate-scene", ["calibrate-scene", "sc6", "--grid", "2x2", "--pitch-mm",
                                                            "10", "--focal-px", "300", "--max-frames", "3", "-o",
                                                            "o.json", "--report-json", "dev_null", "--quiet"],
             use("sc6")),
            ("refine-out-devnull", "refine", ["refine", "sc/original.json", "sc", "-o", "dev_null", "--quiet"], use("sc")),
            ("refine-save-devnull", "refine", ["refine", "sc/original.json", "sc", "-o", "r.json", "--save", "dev_null",
                                               "--quiet"], use("sc")),
            ("export-out-devnull", "export", ["export", "cal.json", "--to", "json", "-o", "dev_null"], use("cal.json")),
            ("export-colmap-devnull", "export", ["export", "cal.json", "--to", "colmap", "-o", "dev_null"],
             use("cal.json")),
            ("import-out-devnull", "import", ["import", "cal_export.json", "--from", "json", "-o", "dev_null"],
             use("cal_export.json")),
            ("demo-out-devnull", "demo", ["demo", "--scene", "small-2x2", "--no-refine", "--jobs", "1", "--quiet",
                                          "--out", "dev_null"], None),
            ("rectify-save-devnull", "rectify", ["rectify", "cal.json", "cb", "-o", "rect", "--save", "dev_null", *Q],
             use("cal.json", "cb"))):
        add(Case(id_, command, "a character device node (standing for /dev/null) as the output", "cli", argv,
                 setup=chain(extra_setup, device("dev_null")), expect="error"))

    # ------------------------------------------------------------------ Python API
    CB = use("cb", "cal.json")  # noqa: N806
    SC = use("sc")  # noqa: N806
    pre_sc = textwrap.dedent("""
        calib = lf.Calibration.load("sc/original.json")
        cap = lf.open_capture("sc", calib.grid)
        frames = list(cap.frames())
    """)
    pre_cb = textwrap.dedent("""
        cap = lf.open_capture("cb", (2, 2))
        board = lf.BoardSpec.parse("7x5", 15)
    """)

    def a(id_, command, desc, code, setup=None, expect="error", **kw):
        api(f"api-{id_}", command, desc, code, setup, expect, **kw)

    # open_capture and CaptureSet
    for key, call, exp in (("none", "lf.open_capture(None, (2, 2))", "error"),
                           ("int", "lf.open_capture(123, (2, 2))", "error"),
                           ("missing", "lf.open_capture('nope', (2, 2))", "error"),
                           ("file", "lf.open_capture('cal.json', (2, 2))", "error"),
                           ("grid-none", "lf.open_capture('cb', None)", "error"),
                           ("grid-00", "lf.open_capture('cb', (0, 0))", "error"),
                           ("grid-1tuple", "lf.open_capture('cb', (2,))", "error"),
                           ("grid-str", "lf.open_capture('cb', '2x2')", "ok"),
                           ("grid-float", "lf.open_capture('cb', (2.5, 2))", "error"),
                           ("grid-neg", "lf.open_capture('cb', (-1, 2))", "error"),
                           ("grid-33", "lf.open_capture('cb', (3, 3))", "error"),
                           ("grid-nparray", "lf.open_capture('cb', np.array([2, 2]))", "either"),
                           ("layout-bogus", "lf.open_capture('cb', (2, 2), layout='bogus')", "error"),
                           ("missing-bogus", "lf.open_capture('cb', (2, 2), missing='bogus')", "error"),
                           ("bytes-path", "lf.open_capture(b'cb', (2, 2))", "either")):
        a(f"open-{key}", "open_capture", call, f"cap = {call}\nassert len(cap) == 8\n", CB, exp)
    for key, call, exp, allowed in (
            ("frame-99", "cap.load_frame(99)", "error", ("IndexError",)),
            ("frame-neg", "cap.load_frame(-1)", "either", ("IndexError",)),
            ("view-99", "cap.load_view(0, 99)", "error", ("IndexError",)),
            ("limit-0", "list(cap.frames(0))", "error", ()),
            ("limit-float", "list(cap.frames(2.5))", "error", ()),
            ("limit-neg", "list(cap.frames(-1))", "error", ()),
            ("frame-str", "cap.load_frame('0')", "error", ()),
            ("frame-float", "cap.load_frame(1.0)", "error", ()),
            ("colour", "f = cap.load_frame(0, grayscale=False); assert f.shape[-1] == 3", "ok", ())):
        a(f"capture-{key}", "open_capture", call, pre_cb + call + "\n", CB, exp, allowed_exc=allowed)
    # detection and pattern calibration
    cal_verdict = textwrap.dedent("""
        s = lf.evaluate(calib, lf.Calibration.load("cb/truth.json")).summary()
        ok = s["rms_fx_px"] < 3 and s["rms_position_mm"] < 1 and s["rms_rotation_deg"] < 0.2
        verdict = ("CORRECT" if ok else "SILENT_WRONG",
                   f"vs truth fx {s['rms_fx_px']:.3g} px, pos {s['rms_position_mm']:.3g} mm, rot {s['rms_rotation_deg']:.3g} deg")
    """)
    obs_pre = pre_cb + "obs, _ = lf.detect_capture(cap, board, jobs=1, progress=False)\n"
    for key, call, exp in (("cap-none", "lf.detect_capture(None, board)", "error"),
                           ("board-none", "lf.detect_capture(cap, None)", "error"),
                           ("board-str", "lf.detect_capture(cap, '7x5')", "error"),
                           ("jobs0", "lf.detect_capture(cap, board, jobs=0, progress=False)", "either"),
                           ("jobs-neg", "lf.detect_capture(cap, board, jobs=-1, progress=False)", "either"),
                           ("jobs-float", "lf.detect_capture(cap, board, jobs=1.5, progress=False)", "either"),
                           ("board-wrong", "lf.detect_capture(cap, lf.BoardSpec.parse('6x4', 15), jobs=1, progress=False)",
                            "error")):
        a(f"detect-{key}", "detect_capture", call, pre_cb + call + "\n", CB, exp)
    for key, call, exp in (("sq0", "lf.BoardSpec.parse('7x5', 0)", "error"),
                           ("sq-neg", "lf.BoardSpec.parse('7x5', -1)", "error"),
                           ("sq-nan", "lf.BoardSpec.parse('7x5', float('nan'))", "error"),
                           ("sq-str", "lf.BoardSpec.parse('7x5', '15')", "either"),
                           ("text", "lf.BoardSpec.parse('abc', 15)", "error"),
                           ("none", "lf.BoardSpec.parse(None, 15)", "error"),
                           ("float-cols", "lf.BoardSpec(7.5, 5, 0.015)", "error"),
                           ("str-cols", "lf.BoardSpec('7', '5', 0.015)", "error"),
                           ("valid", "lf.BoardSpec(7, 5, 0.015)", "ok")):
        a(f"board-{key}", "BoardSpec", call, call + "\n", None, exp)
    for key, call, exp, allowed in (
            ("none", "lf.calibrate(None)", "error", ()),
            ("path", "lf.calibrate('cb')", "error", ()),
            ("dict-config", "lf.calibrate(obs, {'robust': 'huber'})", "error", ()),
            ("robust-bogus", "lf.CalibrateConfig(robust='bogus')", "error", ()),
            ("robust-neg", "lf.CalibrateConfig(robust='huber:-1')", "error", ()),
            ("robust-int", "lf.CalibrateConfig(robust=5)", "error", ()),
            ("method-bogus", "lf.CalibrateConfig(method='bogus')", "error", ()),
            ("boardsigma-neg", "lf.CalibrateConfig(board_sigma_mm=-1)", "error", ()),
            ("cornersigma-0", "lf.CalibrateConfig(corner_sigma_px=0)", "error", ()),
            ("focal-inf", "lf.CalibrateConfig(init='design', focal_px=float('inf'))", "error", ()),
            ("hook-none", "lf.calibrate(obs, lf.CalibrateConfig(graph_hooks=(None,)))", "error", ()),
            ("hook-raises", "lf.calibrate(obs, lf.CalibrateConfig(graph_hooks=(lambda ctx: 1 / 0,)))", "error",
             ("ZeroDivisionError", "RuntimeError")),
            ("observer-object", "lf.calibrate(obs, observer=object())", "error", ())):
        a(f"calibrate-{key}", "calibrate", call, obs_pre + call + "\n", CB, exp, allowed_exc=allowed)
    for key, cfg, exp in (("valid", "None", "ok"), ("maxit0", "lf.CalibrateConfig(max_iterations=0)", "either"),
                          ("maxit-neg", "lf.CalibrateConfig(max_iterations=-5)", "either"),
                          ("maxit-float", "lf.CalibrateConfig(max_iterations=2.5)", "either"),
                          ("nomarginals", "lf.CalibrateConfig(marginals=False)", "ok"),
                          ("tangential", "lf.CalibrateConfig(tangential=True)", "ok"),
                          ("paper", "lf.CalibrateConfig(method='paper')", "ok")):
        a(f"calibrate-cfg-{key}", "calibrate", f"lf.calibrate(obs, {cfg})",
          obs_pre + f"calib, report = lf.calibrate(obs, {cfg})\n" + textwrap.dedent(cal_verdict), CB, exp)
    a("calibrate-obs-one-frame", "calibrate", "observations of one frame",
      obs_pre + "import dataclasses\nobs = dataclasses.replace(obs, corners_px=obs.corners_px[:, :1], "
      "valid=obs.valid[:, :1], frame_names=obs.frame_names[:1], sources=obs.sources[:1])\n"
      "calib, report = lf.calibrate(obs)\n" + textwrap.dedent(cal_verdict), CB, "either")
    a("calibrate-obs-nan", "calibrate", "observations with a NaN corner marked valid",
      obs_pre + "import dataclasses\nc = obs.corners_px.copy(); c[1, 2, 3] = np.nan\n"
      "obs = dataclasses.replace(obs, corners_px=c)\ncalib, report = lf.calibrate(obs)\n"
      + textwrap.dedent(cal_verdict), CB, "error")
    a("calibrate-obs-all-same-frame", "calibrate", "every frame the same board pose (frame 0 repeated)",
      obs_pre + "import dataclasses\nn = obs.num_frames\nobs = dataclasses.replace(obs, corners_px=np.repeat("
      "obs.corners_px[:, :1], n, 1), valid=np.repeat(obs.valid[:, :1], n, 1))\n"
      "calib, report = lf.calibrate(obs)\n" + textwrap.dedent(cal_verdict), CB, "error")
    for key, call, exp in (("valid", "lf.load_detections('points.npz', 'npz', (2, 2), (320, 240))", "ok"),
                           ("fmt-bogus", "lf.load_detections('points.npz', 'bogus', (2, 2), (320, 240))", "error"),
                           ("size0", "lf.load_detections('points.npz', 'npz', (2, 2), (0, 0))", "error"),
                           ("size-none", "lf.load_detections('points.npz', 'npz', (2, 2), None)", "error"),
                           ("path-none", "lf.load_detections(None, 'npz', (2, 2), (320, 240))", "error"),
                           ("grid-none", "lf.load_detections('points.npz', 'npz', None, (320, 240))", "error")):
        a(f"loaddet-{key}", "load_detections", call, f"obs = {call}\nassert obs.valid.any()\n", use("points.npz"), exp)
    # refine
    ref_verdict = textwrap.dedent("""
        truth = lf.Calibration.load("sc/truth.json")
        b, a = lf.evaluate(calib, truth).summary(), lf.evaluate(refined, truth).summary()
        ok = a["rms_rotation_deg"] <= b["rms_rotation_deg"] + 0.02 and a["rms_position_mm"] <= b["rms_position_mm"] + 0.5
        verdict = ("CORRECT" if ok else "SILENT_WRONG",
                   f"rotation {b['rms_rotation_deg']:.3g} -> {a['rms_rotation_deg']:.3g} deg, position "
                   f"{b['rms_position_mm']:.3g} -> {a['rms_position_mm']:.3g} mm")
    """)
    for key, call, exp, allowed in (
            ("calib-none", "lf.refine(None, frames)", "error", ()),
            ("calib-path", "lf.refine('sc/original.json', frames)", "error", ()),
            ("frames-none", "lf.refine(calib, None)", "error", ()),
            ("frames-empty", "lf.refine(calib, [])", "error", ()),
            ("frames-array", "lf.refine(calib, frames[0])", "error", ()),
            ("frames-2d", "lf.refine(calib, [frames[0][0]])", "error", ()),
            ("frames-colour", "lf.refine(calib, [np.repeat(f[..., None], 3, -1) for f in frames])", "error", ()),
            ("frames-uint16", "lf.refine(calib, [f.astype(np.uint16) * 257 for f in frames])", "error", ()),
            ("frames-float", "lf.refine(calib, [f.astype(np.float32) / 255 for f in frames])", "error", ()),
            ("frames-nan", "lf.refine(calib, [np.full(frames[0].shape, np.nan)])", "error", ()),
            ("frames-bool", "lf.refine(calib, [f > 128 for f in frames])", "error", ()),
            ("frames-size", "lf.refine(calib, [np.zeros((4, 100, 100), np.uint8)])", "error", ()),
            ("frames-3views", "lf.refine(calib, [f[:3] for f in frames])", "error", ()),
            ("frames-lists", "lf.refine(calib, [f.tolist() for f in frames])", "error", ()),
            ("frames-strings", "lf.refine(calib, ['sc/000', 'sc/001'])", "error", ()),
            ("frames-gen-raises", "lf.refine(calib, (f if i == 0 else (_ for _ in ()).throw(RuntimeError('camera unplugged')) for i, f in enumerate(frames)))",
             "error", ("RuntimeError",)),
            ("frames-black", "lf.refine(calib, [np.zeros_like(f) for f in frames])", "error", ()),
            ("config-dict", "lf.refine(calib, frames, {'robust': 'huber'})", "error", ()),
            ("observer-object", "lf.refine(calib, frames, observer=object())", "error", ()),
            ("calib-othersize", "lf.refine(lf.Calibration.load('other_size/truth.json'), frames)", "error", ()),
            ("hook-raises", "lf.refine(calib, frames, lf.RefineConfig(graph_hooks=(lambda ctx: 1 / 0,)))", "error",
             ("ZeroDivisionError", "RuntimeError")),
    ):
        a(f"refine-{key}", "refine", call, pre_sc + call + "\n", chain(SC, use("other_size")), exp,
          allowed_exc=allowed)
    for key, cfg, exp in (
            ("stages-bogus", "stages='bogus'", "error"), ("folds1", "folds=1", "error"),
            ("folds-nan", "folds=float('nan')", "error"), ("folds-float", "folds=2.5", "error"),
            ("maxit0", "max_iterations=0", "either"), ("maxit-neg", "max_iterations=-1", "error"),
            ("minimp-nan", "min_improvement=float('nan')", "error"), ("minimp-neg", "min_improvement=-1", "error"),
            ("signif-inf", "significance_sigma=float('inf')", "either"), ("tol-inf", "tolerance_px=float('inf')", "error"),
            ("msigma0", "measurement_sigma_px=0", "error"), ("msigma-tiny", "measurement_sigma_px=1e-300", "either"),
            ("maxframes0", "max_frames=0", "error"), ("maxframes-float", "max_frames=1.5", "error"),
            ("target-neg", "target_rms_px=-1", "error"), ("target-nan", "target_rms_px=float('nan')", "error"),
            ("scale-nan", "scale_sigma_mm=float('nan')", "error"), ("scale1", "scale_sigma_mm=1.0", "ok"),
            ("maxlm5", "max_landmarks=5", "error"), ("maxlm-nan", "max_landmarks=float('nan')", "error"),
            ("minobs-neg", "min_view_observations=-1", "error"), ("minobs-huge", "min_view_observations=10**9", "either"),
            ("drift-bogus", "drift='bogus'", "error"), ("drift-zero", "drift=lf.refinement.config.DriftModel(roll_deg=0)",
                                                        "error"),
            ("robust-huber-gtsam", "robust=__import__('gtsam').noiseModel.mEstimator.Huber.Create(1.345)", "ok"),
            ("robust-wrongdim", "robust=__import__('gtsam').noiseModel.Isotropic.Sigma(3, 1.0)", "error"),
            ("robust-object", "robust=object()", "error"), ("uncertain-nan", "uncertain_transfer_px=float('nan')", "error"),
            ("trifilter-bogus", "triangulation_filter='bogus'", "error"), ("clean-bogus", "clean_robust='bogus'", "error"),
            ("free-nofolds", "priors=False, folds=0", "ok"), ("match-str", "match='bogus'", "error"),
            ("stages-list", "stages=['points', 'poses']", "ok"), ("stages-enum-bad", "stages=[1, 2]", "error"),
    ):
        a(f"refinecfg-{key}", "RefineConfig", f"lf.RefineConfig({cfg}) then refine",
          pre_sc + f"cfg = lf.RefineConfig({cfg})\nrefined, report = lf.refine(calib, frames, cfg)\n"
          + textwrap.dedent(ref_verdict), SC, exp)
    a("refine-valid", "refine", "lf.refine(calib, frames) (valid)",
      pre_sc + "refined, report = lf.refine(calib, frames)\n" + textwrap.dedent(ref_verdict), SC, "ok")
    a("refine-fortran", "refine", "frames in Fortran order (valid data, other memory layout)",
      pre_sc + "refined, report = lf.refine(calib, [np.asfortranarray(f) for f in frames])\n"
      + textwrap.dedent(ref_verdict), SC, "ok")
    a("refine-readonly", "refine", "read-only frame arrays",
      pre_sc + "[f.setflags(write=False) for f in frames]\nrefined, report = lf.refine(calib, frames)\n"
      + textwrap.dedent(ref_verdict), SC, "ok")
    a("refine-generator", "refine", "frames as a generator (capture.frames())",
      pre_sc + "refined, report = lf.refine(calib, cap.frames())\n" + textwrap.dedent(ref_verdict), SC, "ok")
    # check / evaluate / rectify
    for key, call, exp in (("calib-none", "lf.check(None, frames)", "error"),
                           ("frames-empty", "lf.check(calib, [])", "error"),
                           ("frames-colour", "lf.check(calib, [np.repeat(f[..., None], 3, -1) for f in frames])", "error"),
                           ("frames-nan", "lf.check(calib, [np.full(frames[0].shape, np.nan)])", "error"),
                           ("settings-bogus", "lf.check(calib, frames, settings='bogus')", "error"),
                           ("frames-none", "lf.check(calib, None)", "error")):
        a(f"check-{key}", "check", call, pre_sc + call + "\n", SC, exp)
    a("check-valid", "check", "lf.check on a shaken rig finds the drift",
      pre_sc + "rep = lf.check(calib, frames)\nd = rep.drifted()\n"
      "verdict = ('CORRECT' if d else 'SILENT_WRONG', f'drifted views: {d}')\n", SC, "ok")
    for key, call, exp in (("none", "lf.evaluate(None, truth)", "error"),
                           ("paths", "lf.evaluate('cal.json', 'cb/truth.json')", "error"),
                           ("grid", "lf.evaluate(calib, lf.Calibration.load('cb12/truth.json'))", "error"),
                           ("self", "e = lf.evaluate(calib, calib); assert max(e.summary().values()) == 0", "ok")):
        a(f"evaluate-{key}", "evaluate", call, "calib = lf.Calibration.load('cal.json')\n"
          "truth = lf.Calibration.load('cb/truth.json')\n" + call + "\n", chain(CB, use("cb12")), exp)
    rect_pre = "calib = lf.Calibration.load('cal.json')\n"
    for key, call, exp in (("none", "lf.rectify(None)", "error"), ("crop-bogus", "lf.rectify(calib, crop='bogus')", "error"),
                           ("k1-50", "lf.rectify(calib.replace(intrinsics=tuple(i if v != 1 else __import__('dataclasses').replace(i, k1=50.0) for v, i in enumerate(calib.intrinsics))))", "error"),
                           ("same-pos", "T = calib.ref_T_view.copy(); T[:, :3, 3] = 0\nlf.rectify(calib.replace(ref_T_view=T))", "error"),
                           ("huge-size", "lf.rectify(calib.replace(image_size_px=(100000, 100000)))", "either"),
                           ("valid", "r = lf.rectify(calib); assert r.rectification is not None", "ok")):
        a(f"rectify-{key}", "rectify", call, rect_pre + call + "\n", CB, exp)
    # Calibration files and objects
    for key, call, exp in (("none", "lf.Calibration.load(None)", "error"), ("int", "lf.Calibration.load(123)", "error"),
                           ("dir", "lf.Calibration.load('cb')", "error"), ("devnull", "lf.Calibration.load('dev_null')", "error"),
                           ("fifo", "lf.Calibration.load('f.json')", "error"),
                           ("deep", "lf.Calibration.load('deep.json')", "error"),
                           ("bytes", "lf.Calibration.load(b'cal.json')", "either"),
                           ("fromdict-none", "lf.Calibration.from_dict(None)", "error"),
                           ("fromdict-list", "lf.Calibration.from_dict([])", "error"),
                           ("fromdict-numpy", "d = json.load(open('cal.json'))\nfor v in d['views']: v['K'] = np.array(v['K'])\nlf.Calibration.from_dict(d)", "either"),
                           ("fromdict-npint", "d = json.load(open('cal.json'))\nd['image_size_px'] = [np.int64(320), np.int64(240)]\nlf.Calibration.from_dict(d)", "either")):
        a(f"load-{key}", "Calibration.load", call, "import json\n" + call + "\n",
          chain(CB, fifo("f.json"), device("dev_null"), put("deep.json", "[" * 100000 + "]" * 100000)), exp)
    obj_pre = "import dataclasses\ncalib = lf.Calibration.load('cal.json')\nI = calib.intrinsics\n"
    for key, call, exp, allowed in (
            ("3-intrinsics", "lf.Calibration(calib.grid, (320, 240), I[:3], calib.ref_T_view)", "error", ()),
            ("poses-nan", "T = calib.ref_T_view.copy(); T[1, 0, 3] = np.nan\nlf.Calibration(calib.grid, (320, 240), I, T)", "error", ()),
            ("size0", "lf.Calibration(calib.grid, (0, 0), I, calib.ref_T_view)", "error", ()),
            ("size-none", "lf.Calibration(calib.grid, None, I, calib.ref_T_view)", "error", ()),
            ("size-float", "c = lf.Calibration(calib.grid, (320.7, 240.2), I, calib.ref_T_view)\nverdict = ('SILENT_WRONG', f'accepted: image_size_px (320.7, 240.2) became {c.image_size_px}')", "error", ()),
            ("fx-nan", "lf.Calibration(calib.grid, (320, 240), (dataclasses.replace(I[0], fx=float('nan')),) + I[1:], calib.ref_T_view)", "error", ()),
            ("fx-inf", "lf.Intrinsics(float('inf'), 300, 160, 120)", "error", ()),
            ("k1-nan", "lf.Intrinsics(300, 300, 160, 120, float('nan'))", "error", ()),
            ("save-dir", "calib.save('cb')", "error", ()),
            ("save-newdirs", "calib.save('new/dirs/x.json'); assert lf.Calibration.load('new/dirs/x.json')", "either", ()),
            ("save-fifo", "calib.save('f.json')", "either", ()),
            ("save-devnull", "calib.save('dev_null')", "either", ()),
            ("save-np-metric", "calib.replace(metrics={'x': np.float32(1)}).save('m.json')", "either", ()),
            ("save-nan-metric", "calib.replace(metrics={'x': float('nan')}).save('m.json')", "error", ()),
            ("save-obj-metric", "calib.replace(metrics={'x': object()}).save('m.json')", "error", ()),
            ("replace-size", "calib.replace(image_size_px=(-1, 5))", "error", ()),
            ("grid-float", "g = lf.ViewGrid(2.5, 2); n = g.num_views", "error", ()),
            ("grid-zero", "lf.ViewGrid(0, 2)", "error", ()),
            ("grid-ref", "lf.ViewGrid(2, 2, 9)", "error", ()),
            ("grid-str", "lf.ViewGrid('2', 2)", "error", ())):
        a(f"obj-{key}", "Calibration", call, obj_pre + call + "\n", chain(CB, fifo("f.json"), device("dev_null")), exp,
          allowed_exc=allowed, mutable=(r"^f\.json$", r"^dev_null$") if key in ("save-fifo", "save-devnull") else ())
    for key, call, exp in (("bogus", "lf.RobustKernel('bogus')", "error"), ("neg", "lf.RobustKernel('huber', -1)", "error"),
                           ("nan", "lf.RobustKernel('huber', float('nan'))", "error"),
                           ("none-name", "lf.RobustKernel(None)", "error"), ("parse-int", "lf.RobustKernel.parse(5)", "error"),
                           ("str-threshold", "lf.RobustKernel('huber', '1.0')", "error"),
                           ("valid", "lf.RobustKernel.parse('cauchy:0.5').estimator()", "ok")):
        a(f"kernel-{key}", "RobustKernel", call, call + "\n", None, exp)
    for key, call, exp in (("scene-bogus", "__import__('lfgraph.datasets.scenes').datasets.scenes.get_scene('bogus')", "error"),
                           ("scene-none", "__import__('lfgraph.datasets.scenes').datasets.scenes.get_scene(None)", "error"),
                           ("rig-rows0", "from lfgraph.datasets.rig import RigConfig, make_rig\nmake_rig(RigConfig(rows=0, cols=2), np.random.default_rng(0))", "error"),
                           ("rig-focal-neg", "from lfgraph.datasets.rig import RigConfig, make_rig\nmake_rig(RigConfig(rows=2, cols=2, focal_px=-300), np.random.default_rng(0))", "error"),
                           ("rig-size0", "from lfgraph.datasets.rig import RigConfig, make_rig\nmake_rig(RigConfig(rows=2, cols=2, image_size_px=(0, 0)), np.random.default_rng(0))", "error"),
                           ("shake-nan", "from lfgraph.datasets.rig import ShakeConfig, shake_rig\nc = lf.Calibration.load('cal.json')\nshake_rig(c, ShakeConfig(rot_deg=float('nan')), np.random.default_rng(0))", "error"),
                           ("point-board", "lf.PointBoard(np.zeros((3, 3)))", "error"),
                           ("point-board-2d", "lf.PointBoard(np.zeros((10, 2)))", "error")):
        a(f"datasets-{key}", "datasets", call, call + "\n", CB, exp)
    for key, call, exp in (("dir", "lf.viz.RerunLogger.to_file('cb', lf.ViewGrid(2, 2))", "error"),
                           ("missing-dir", "r = lf.viz.RerunLogger.to_file('nope/x.rrd', lf.ViewGrid(2, 2))\nwith r: pass", "either"),
                           ("valid", "r = lf.viz.RerunLogger.to_file('x.rrd', lf.ViewGrid(2, 2))\nwith r: pass\nassert Path('x.rrd').stat().st_size > 0", "ok"),
                           ("exception-inside", "r = lf.viz.RerunLogger.to_file('x.rrd', lf.ViewGrid(2, 2))\nwith r: raise KeyError('user bug')", "error")):
        a(f"viz-{key}", "viz", call, call + "\n", CB, exp, allowed_exc=("KeyError",) if key == "exception-inside" else ())

    cli("import-kalibr-wrong-grid", "import", "a 2x2 Kalibr camchain imported as --grid 4x1",
        ["import", "camchain.yaml", "--from", "kalibr", "--grid", "4x1", "-o", "o.json"], use("camchain.yaml"))
    cli("fleet-manifest-column-twice", "fleet", "a manifest naming max_px twice", ["fleet", "m.csv", "-o", "r.csv"],
        chain(use("sc"), put("m.csv", "camera,calibration,capture,max_px,max_px\ncam1,sc/original.json,sc,1,2\n")))
    # validation at the API's door (issue 42, third round)
    for key, call in (("intrinsics-bool", "lf.Intrinsics(True, 300, 160, 120)"),
                      ("image-size-out", "lf.Calibration.load('cal.json').image_size(4)"),
                      ("image-size-neg", "lf.Calibration.load('cal.json').image_size(-1)"),
                      ("image-size-float", "c = lf.Calibration.load('cal.json')\n"
                                           "c.replace(view_image_sizes_px=((320.5, 240),) * 4)"),
                      ("design-size-float", "lf.Design(rows=2, cols=2, pitch_mm=10, focal_px=300, "
                                            "image_size_px=(640.5, 480))"),
                      ("vectorised-none", "lf.vectorised_estimator(None, None)"),
                      ("vectorised-negative", "lf.vectorised_estimator(lambda d: -np.ones_like(d), lambda d: d * d)"),
                      ("config-lens-bogus", "lf.CalibrateConfig(lens='bogus')")):
        a(f"door-{key}", "api-door", call, call + "\n", CB, "error")

    return cases


# ============================================================================================ main
def describe_call(case: Case) -> str:
    import shlex

    if case.kind == "api":
        return "python: " + case.code.strip().replace("\n", " ; ")
    if case.kind == "shell":
        return case.code.replace("LFG", "lfgraph")
    cmd = "lfgraph " + shlex.join(case.argv)
    if case.kind == "sigint":
        return f"{cmd}   # Ctrl-C (SIGINT to the group) after {case.delay:g} s"
    if case.kind == "sigkill":
        return f"{cmd}   # kill -9 of the parent after {case.delay:g} s"
    if case.kind == "popen-kill":
        return f"{cmd}   # Popen(stdout=PIPE, stderr=PIPE).communicate(timeout={case.delay:g}), kill(), communicate()"
    if case.kind == "pipe":
        return f"{cmd} | head -c {int(case.delay)}"
    return cmd


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", help="regex: run only the cases whose id matches")
    ap.add_argument("--list", action="store_true", help="list the cases and exit")
    ap.add_argument("--regen", action="store_true", help="generate the data again")
    ap.add_argument("--keep", action="store_true", help="keep every case folder (default: only the failing ones)")
    ap.add_argument("--csv", default=str(OUT / "trial.csv"))
    args = ap.parse_args()
    cases = build_cases()
    ids = Counter(c.id for c in cases)
    dup = [k for k, n in ids.items() if n > 1]
    if dup:
        raise SystemExit(f"duplicate case ids: {dup}")
    if args.only:
        cases = [c for c in cases if re.search(args.only, c.id)]
    if args.list:
        for c in cases:
            print(f"{c.id:45s} {c.command:18s} {c.desc}")
        print(len(cases), "cases")
        return 0
    t_start = time.time()
    make_data(args.regen)
    HARNESS.write_text(HARNESS_CODE)
    if CASES_DIR.exists():
        shutil.rmtree(CASES_DIR)
    CASES_DIR.mkdir(parents=True)
    data_before = snapshot(DATA)
    rows = []
    print(f"running {len(cases)} cases sequentially (timeout {DEFAULT_TIMEOUT_S:.0f} s each)", flush=True)
    for n, case in enumerate(cases, 1):
        d = CASES_DIR / case.id
        d.mkdir()
        try:
            if case.setup is not None:
                case.setup(d)
        except Exception as exc:  # noqa: BLE001
            raise SystemExit(f"setup of {case.id} failed: {exc!r}") from exc
        before = snapshot(d)
        try:
            res = run_case(case, d)
            changed, new = diff_snapshots(before, snapshot(d))
            cls, note = classify(case, d, res, changed, new)
        finally:
            if case.teardown is not None:
                case.teardown(d)
        rows.append({"id": case.id, "command": case.command, "description": case.desc, "class": cls,
                     "exit_code": "timeout" if res.timed_out else res.rc, "seconds": f"{res.seconds:.2f}",
                     "stderr_first_line": first_line(res.stderr),
                     "message": (f"{res.api['type']}: {res.api['msg']}" if case.kind == "api" and res.api
                                 and res.api.get("status") == "exc" else message_line(res.stderr)),
                     "note": note, "call": describe_call(case)})
        print(f"[{n:3d}/{len(cases)}] {cls:12s} {res.seconds:5.1f}s rc={rows[-1]['exit_code']!s:7s} {case.id}"
              + (f"  -- {note[:110]}" if cls not in ("CLEAR_ERROR", "CORRECT") else ""), flush=True)
        if cls in ("CLEAR_ERROR", "CORRECT") and not args.keep:
            shutil.rmtree(d, ignore_errors=True)
            for suffix in (".stdout", ".stderr", ".snippet.py", ".result.json"):
                (CASES_DIR / f"{case.id}{suffix}").unlink(missing_ok=True)
    data_after = snapshot(DATA)
    changed, new = diff_snapshots(data_before, data_after)
    elapsed = time.time() - t_start
    with open(args.csv, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    # summary
    counts = Counter(r["class"] for r in rows)
    print("\n== counts per class")
    for c in CLASSES:
        print(f"  {c:12s} {counts.get(c, 0):4d}")
    print(f"  {'total':12s} {len(rows):4d}")
    per_cmd: dict[str, Counter] = defaultdict(Counter)
    for r in rows:
        per_cmd[r["command"]][r["class"]] += 1
    short = {"CLEAR_ERROR": "CLEAR", "CORRECT": "OK", "TRACEBACK": "TB", "INTERNAL": "INT", "HANG": "HANG",
             "DATA_LOSS": "LOSS", "SILENT_WRONG": "SILENT"}
    print("\n== per command")
    print(f"  {'command':22s}" + "".join(f"{short[c]:>7s}" for c in CLASSES) + f"{'total':>7s}")
    for cmd in sorted(per_cmd):
        cnt = per_cmd[cmd]
        print(f"  {cmd:22s}" + "".join(f"{cnt.get(c, 0):7d}" for c in CLASSES) + f"{sum(cnt.values()):7d}")
    bad = [r for r in rows if r["class"] not in ("CLEAR_ERROR", "CORRECT")]
    print(f"\n== {len(bad)} cases neither CLEAR_ERROR nor CORRECT")
    with open(OUT / "failures.txt", "w") as fh:
        for r in bad:
            block = (f"[{r['class']}] {r['id']} ({r['command']}): {r['description']}\n  call: {r['call']}\n"
                     f"  exit {r['exit_code']}, {r['seconds']} s; {r['note']}\n  stderr: {r['message']}\n")
            print(block, end="")
            fh.write(block)
            err = CASES_DIR / f"{r['id']}.stderr"
            if err.exists():
                fh.write(textwrap.indent(err.read_text(errors="replace")[-3000:], "    | ") + "\n")
    refused = [r for r in rows if r["class"] == "CLEAR_ERROR" and "should work" in r["note"]]
    if refused:
        print(f"\n== {len(refused)} valid-but-unusual inputs refused with a clear error")
        for r in refused:
            print(f"  {r['id']}: {r['message'][:150]}")
    if changed or new:
        print(f"\n!! the shared data under {DATA} changed during the trial: {changed[:5]} {new[:5]}")
    print(f"\n{len(rows)} cases in {elapsed / 60:.1f} min; CSV: {args.csv}; details: {OUT / 'failures.txt'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
