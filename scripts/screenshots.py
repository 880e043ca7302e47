"""Make the README's pictures (``make screenshots``; opt-in, not part of ``make test``).

1. Runs ``lfgraph`` on small synthetic data: calibrate, refine (a shaken rig) and rectify with ``--save``, refine of
   a shaken 5x5, 1x8 and fisheye 1x3, the shake and calibration studies, ``calibrate --plots``.
2. Renders the recordings in rerun's web viewer (``rerun --serve-web``, bound to 127.0.0.1) in headless Chromium
   (software WebGL: ``--use-angle=swiftshader``, ``&renderer=webgl``), driven over the DevTools protocol (tornado's
   websocket client: the ``test`` extras bring it): the refine runs as they open (their own layout, as a user sees
   them), the others each with a blueprint that frames one thing.
3. Writes small PNGs to ``docs/images/`` (quantised to `PNG_COLOURS` colours when Pillow is there).

Needs the Debian package ``chromium``. Look at every picture before committing it.

    python scripts/screenshots.py [--out docs/images] [--work DIR] [--keep]
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import rerun.blueprint as rrb

from lfgraph.cli import main as lfgraph

WINDOW_PX = (1400, 860)
VIEWER_LOAD_S = 60.0  # real time for the web viewer to load its wasm and the recording, decode the JPEGs, draw
# refine recordings shown as they open: (scene, extra synth arguments, picture); 2 frames, 1 deg / 3 mm shake
RIGS = (("paper-5x5", [], "rerun_refine_5x5.png"), ("paper-5x5", ["--grid", "1x8"], "rerun_refine_1x8.png"),
        ("fisheye-1x3", [], "rerun_refine_fisheye_1x3.png"))
PNG_COLOURS = 256
APP_ID = "lfgraph"
CHROMIUM_FLAGS = ("--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                  "--hide-scrollbars", "--remote-allow-origins=*", "--remote-debugging-address=127.0.0.1",
                  "--no-first-run", "--mute-audio")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def stop_group(proc: subprocess.Popen) -> None:
    """End a process started with ``start_new_session=True`` and everything it started (its own process group:
    the ``rerun`` wrapper's viewer binary, Chromium's helpers)."""
    try:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=20)
    except ProcessLookupError:
        pass
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=20)


def wait_http(url: str, timeout_s: float = 30.0) -> None:
    end = time.monotonic() + timeout_s
    while True:
        try:
            with urllib.request.urlopen(url, timeout=2):
                return
        except OSError:
            if time.monotonic() > end:
                raise
            time.sleep(0.3)


def cdp_screenshot(page_url: str, out_png: Path, wait_s: float) -> None:
    """Open ``page_url`` in headless Chromium, wait ``wait_s`` real seconds, write a PNG screenshot."""
    from tornado.ioloop import IOLoop
    from tornado.websocket import websocket_connect

    port = free_port()
    profile = tempfile.mkdtemp(prefix="lfgraph-chromium-")
    chrome = subprocess.Popen(["chromium", *CHROMIUM_FLAGS, f"--remote-debugging-port={port}",
                               f"--window-size={WINDOW_PX[0]},{WINDOW_PX[1]}", f"--user-data-dir={profile}",
                               "about:blank"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                              start_new_session=True)
    try:
        wait_http(f"http://127.0.0.1:{port}/json/version")
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list") as r:
            page = next(t for t in json.load(r) if t["type"] == "page")

        async def run() -> bytes:
            ws = await websocket_connect(page["webSocketDebuggerUrl"], max_message_size=256 * 2**20)
            ids = iter(range(1, 1_000_000))

            async def call(method: str, **params) -> dict:
                i = next(ids)
                ws.write_message(json.dumps({"id": i, "method": method, "params": params}))
                while True:
                    msg = json.loads(await ws.read_message())
                    if msg.get("id") == i:
                        return msg.get("result", {})

            await call("Emulation.setDeviceMetricsOverride", width=WINDOW_PX[0], height=WINDOW_PX[1],
                       deviceScaleFactor=1, mobile=False)
            await call("Page.navigate", url=page_url)
            end = time.monotonic() + wait_s
            while time.monotonic() < end:  # keep reading events so the socket does not back up
                try:
                    await asyncio.wait_for(ws.read_message(), timeout=0.5)
                except TimeoutError:
                    pass
            shot = await call("Page.captureScreenshot", format="png")
            ws.close()
            return base64.b64decode(shot["data"])

        out_png.write_bytes(IOLoop.current().run_sync(run, timeout=wait_s + 60))
    finally:
        stop_group(chrome)
        shutil.rmtree(profile, ignore_errors=True)


def render_recording(rrd: Path, blueprint: rrb.Blueprint | None, out_png: Path, work: Path) -> None:
    """Serve ``rrd`` with ``blueprint`` (saved as .rbl; None: the recording's own layout) in rerun's web viewer and
    screenshot it."""
    files = [str(rrd)]
    if blueprint is not None:
        # the recording's own layout is made active when it loads: a copy of its data alone takes the .rbl's
        from rerun.chunk import RrdReader

        data = work / f"{out_png.stem}.data.rrd"
        reader = RrdReader(rrd)
        reader.stream().write_rrd(data, application_id=APP_ID, recording_id=reader.recordings()[0].recording_id)
        rbl = work / f"{out_png.stem}.rbl"
        blueprint.save(APP_ID, str(rbl))
        files = [str(data), str(rbl)]
    web, grpc = free_port(), free_port()
    rerun = shutil.which("rerun", path=str(Path(sys.executable).parent)) or "rerun"
    server = subprocess.Popen([rerun, "--serve-web", "--bind", "127.0.0.1", "--web-viewer-port", str(web),
                               "--port", str(grpc), *files],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        wait_http(f"http://127.0.0.1:{web}/")
        url = (f"http://127.0.0.1:{web}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc}%2Fproxy"
               "&renderer=webgl&hide_welcome_screen=true")
        cdp_screenshot(url, out_png, VIEWER_LOAD_S)
    finally:
        stop_group(server)


def shrink(png: Path) -> None:
    """Quantise to `PNG_COLOURS` colours (Pillow, when installed) to keep the repository small."""
    try:
        from PIL import Image
    except ImportError:
        return
    Image.open(png).convert("RGB").quantize(PNG_COLOURS).save(png, optimize=True)


def run(cmd: list[str], made: Path | None = None) -> None:
    """``lfgraph cmd``, skipped when it already ``made`` its output (a re-run with the same --work resumes)."""
    if made is not None and made.exists():
        print(f"have {made}", flush=True)
        return
    print("lfgraph", " ".join(cmd), flush=True)
    if lfgraph(cmd) != 0:
        raise SystemExit(f"lfgraph {' '.join(cmd)} failed")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("docs/images"))
    ap.add_argument("--work", type=Path, help="working folder (default: a temporary one)")
    ap.add_argument("--keep", action="store_true", help="keep the working folder")
    ap.add_argument("--no-viewer", action="store_true", help="figures only, no rerun screenshots")
    args = ap.parse_args(argv)
    if not args.no_viewer and shutil.which("chromium") is None:
        raise SystemExit("chromium is missing (Debian: apt-get install chromium), or pass --no-viewer")
    work = args.work or Path(tempfile.mkdtemp(prefix="lfgraph-shots-"))
    work.mkdir(parents=True, exist_ok=True)
    args.out.mkdir(parents=True, exist_ok=True)
    try:
        make(work, args.out, viewer=not args.no_viewer)
    finally:
        if args.work is None and not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    return 0


def make(work: Path, out: Path, viewer: bool) -> None:
    from lfgraph.core.grid import ViewGrid

    grid = ViewGrid(2, 2, 0)
    board, scene = work / "board", work / "scene"
    run(["synth", "checkerboard", str(board), "--scene", "small-2x2", "--frames", "10", "--jobs", "2", "--quiet",
         "--seed", "5"], board / "truth.json")
    run(["calibrate", str(board), "--grid", "2x2", "--board", "7x5", "--square-mm", "15", "--quiet",
         "-o", str(work / "calib.json"), "--save", str(work / "calibrate.rrd"), "--plots", str(work / "report")],
        work / "calibrate.rrd")
    run(["synth", "scene", str(scene), "--scene", "small-2x2", "--frames", "2", "--shake-rot-deg", "1",
         "--shake-trans-mm", "2", "--jobs", "2", "--quiet"], scene / "original.json")
    run(["refine", str(scene / "original.json"), str(scene), "-o", str(work / "refined.json"), "--quiet",
         "--save", str(work / "refine.rrd")], work / "refine.rrd")
    run(["rectify", str(work / "refined.json"), str(scene), "-o", str(work / "rectified"), "--quiet", "--jobs", "2",
         "--save", str(work / "rectify.rrd")], work / "rectify.rrd")
    # the studies resume from their CSVs by themselves
    run(["study", "shake", "--scene", "small-2x2", "--rot-deg", "0,0.25,0.5,1", "--trans-mm", "0,0.5,1,2",
         "--trials", "3", "--stages", "paper,default", "--jobs", "2", "--quiet", "-o", str(work / "shake.csv")])
    run(["study", "calibration", "--scene", "small-2x2", "--frames", "3,5,8", "--sigma-px", "0.1,0.5", "--trials",
         "3", "--jobs", "2", "--quiet", "-o", str(work / "calibration.csv")])
    for src, name in ((work / "shake.png", "shake_study.png"), (work / "calibration.png", "calibration_study.png"),
                      (work / "report" / "residuals.png", "calibration_residuals.png")):
        shutil.copyfile(src, out / name)
        shrink(out / name)
    rigs = [refine_rig(work, rig_scene, extra) for rig_scene, extra, _ in RIGS]
    if not viewer:
        return
    from lfgraph.core.calibration import Calibration
    from lfgraph.viz.blueprint import rig_eye

    refined = Calibration.load(work / "refined.json")
    # paused: a playing timeline shows each frame's points while its image is still being decoded
    paused = rrb.TimePanel(timeline="frame", play_state="paused", state="collapsed")
    rig_view = rrb.Spatial3DView(
        origin="world", name="input (grey) and refined (green) rig; arrows: the change per view",
        contents=["+ /world/input_rig/**", "+ /world/refined_rig/**", "+ /world/change/**"],
        eye_controls=rig_eye(refined))
    shots = [
        ("refine.rrd", rrb.Blueprint(rig_view, paused, collapse_panels=True), "rerun_refine_rig.png"),
        ("calibrate.rrd", rrb.Blueprint(rrb.Spatial2DView(origin="views/r01_c01", name="r01_c01"), paused,
                                        collapse_panels=True), "rerun_residuals.png"),
        ("rectify.rrd", rrb.Blueprint(rrb.Grid(*[rrb.Spatial2DView(origin=f"rectified/{grid.name(v)}",
                                                                   name=grid.name(v)) for v in range(4)],
                                               grid_columns=2), collapse_panels=True), "rerun_rectified.png"),
        *((rrd, None, name) for rrd, (_, _, name) in zip(rigs, RIGS, strict=True)),
    ]
    for rrd, blueprint, name in shots:
        print(f"rendering {rrd} -> {name}", flush=True)
        render_recording(work / rrd, blueprint, out / name, work)
        shrink(out / name)


def refine_rig(work: Path, scene: str, extra: list[str]) -> str:
    """A shaken ``scene`` (2 frames, 1 deg / 3 mm) refined with ``--save``: the recording's name in ``work``."""
    name = "_".join([scene, *extra]).replace("--", "").replace(" ", "")
    folder = work / name
    run(["synth", "scene", str(folder), "--scene", scene, *extra, "--frames", "2", "--shake-rot-deg", "1",
         "--shake-trans-mm", "3", "--jobs", "2", "--quiet"], folder / "original.json")
    run(["refine", str(folder / "original.json"), str(folder), "-o", str(work / f"{name}.json"), "--quiet",
         "--save", str(work / f"{name}.rrd")], work / f"{name}.rrd")
    return f"{name}.rrd"


if __name__ == "__main__":
    sys.exit(main())
