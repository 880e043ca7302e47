"""Renderer speed and accuracy: the renderers before issue 16 ("old"), today's ("new") and a plain OpenCV peer.

Cases, all measured in this run on this machine:

* ``paper-5x5`` textured scene frame: 25 views of 512x512, 2x2 samples per pixel, as ``lfgraph synth scene``.
  The new renderer writes the whole frame with ``write_scene_dataset`` (``--jobs`` processes; start-up, scene
  generation and PNGs included). Old, new and peer each render ``--old-views`` views in this process (lens rays
  cold), twice: noise-free (the render alone: ``render`` columns, accuracy) and as each writer does per image
  (noise, PNG encoding: ``image`` columns). The old frame is extrapolated as the new frame plus (old - new) per
  image x 25 views (wall: / ``--jobs``), plus the scene generation the old writer repeated in each of its tasks
  (CPU only: they ran in parallel; the new writer draws a split frame's scene once).
* ``paper-4x4`` checkerboard set: 16 views x 40 frames of 960x960. The new renderer writes the whole set with
  ``write_checkerboard_dataset``. Old and new render ``--old-frames`` frames of ``--old-views`` views in this
  process (each view's rays computed once, timed apart: CPU ms per view in the note), noise-free and as the
  writers do; the old set is extrapolated the same way, swapping the per-view rays too.
* ``test rig`` checkerboards (the accuracy case of tests/detect/test_checkerboard.py: 2x2 views of 640x480, k1 = -0.12,
  noise-free, blur 0.8 px): RMS of OpenCV-detected corners vs the true projections; the test's limit is 0.05 px.

Like with like: each writer is timed with its own PNG parameters and noise source. The old writers and the new
scene writer use OpenCV's defaults (``cv2.imwrite`` without parameters: zlib level 1, RLE, SUB filter); the new
board writer encodes noisy renders unfiltered with Huffman coding only (`checkerboard.png_params`: the same pixels,
~6 % smaller files, ~20 % less time). Noise: old ``Generator.standard_normal`` in float64, new a 16-bit Gaussian
quantile lookup (`lfgraph.datasets.render.to_uint8`). PNG encoding (~7-9 ms per noisy 960x960 board, ~3 ms per
512x512 view) costs about as much as the whole new render and bounds the set's speed-up; the
``x_old_render_cpu`` column is the renderer's own (noise-free image in memory).

The peer does the least an OpenCV user would: per view, ``cv2.warpPerspective`` (bilinear) of each planar texture
into a pinhole image of the view's size (painter's order, far to near; a board drawn at 40 px per square) and the
lens applied with ``cv2.remap`` through a map from ``cv2.undistortPoints`` (once per lens); no anti-aliasing, no
noise, no margin for the lens (barrel-distorted corners see background), PNG encoding as the writers, one process
(its wall time divided by ``--jobs``).

Columns: wall and CPU time per view (ms) of the render alone and of a written image, and per set (s); speed vs
old (render: CPU; set: wall and CPU) and vs the peer (``x_peer``: peer time / this time, > 1 = faster than the
peer); RMS of detected corners vs truth (px; detection may fail on a few peer images); mean absolute grey-level
difference from the old renderer (noise-free renders of the same views). The machine is shared: wall times swing
with the other users' load, CPU times (this process plus the writers' worker pools) much less; compare ratios
from the same run.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from render_reference import ViewRays as OldViewRays
from render_reference import (
    render_checkerboard_view_reference,
    render_scene_depth_reference,
    render_scene_view_reference,
)

from lfgraph.cli.tables import format_table
from lfgraph.datasets.board_render import ViewRays, render_checkerboard_view
from lfgraph.datasets.checkerboard import (
    CheckerboardConfig,
    make_checkerboard_truth,
    png_params,
    write_checkerboard_dataset,
)
from lfgraph.datasets.render import sample_rays
from lfgraph.datasets.rig import RigConfig, make_rig
from lfgraph.datasets.scene import SceneConfig, make_scene, render_scene_depth, render_scene_views, write_scene_dataset
from lfgraph.datasets.scenes import get_scene
from lfgraph.detect.board import BoardSpec
from lfgraph.detect.chessboard import detect_board

SCENE_FRAME_TARGET_S = 2.0  # issue 16: a paper-5x5 scene frame
BOARD_SET_TARGET_S = 60.0  # issue 16: the paper-4x4 board set
CORNER_RMS_LIMIT_PX = 0.05  # tests/detect/test_checkerboard.py
SPEEDUP_TARGET = 20.0  # issue 16, for the renderers
PEER_PX_PER_SQUARE = 40
PEER_BACKGROUND = 120
PEER_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-9)


# ---------------------------------------------------------------------------------------------- the OpenCV peer
def _peer_lens_map(intr, size):
    """For every distorted pixel, its undistorted pixel: OpenCV's iterative undistortion of the pixel grid.

    (``cv2.initUndistortRectifyMap`` gives the opposite direction, undistorted -> distorted, used to undistort.)
    """
    w, h = size
    grid = np.stack(np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32)), axis=-1)
    und = cv2.undistortPoints(grid.reshape(-1, 1, 2), intr.K, intr.dist_cv, None, None, intr.K, PEER_UNDISTORT_CRITERIA)
    return cv2.convertMaps(und.reshape(h, w, 2), None, cv2.CV_16SC2)


def peer_board_view(intr, size, view_T_board, board: BoardSpec, maps, texture=None):  # noqa: N803
    """The board warped into the pinhole image, then distorted by remap."""
    s, m = board.square_m, board.margin_squares
    if texture is None:
        texture = peer_board_texture(board)
    o = s * (0.5 / PEER_PX_PER_SQUARE - (1 + m))  # board metres of texel (0, 0)
    A = np.array([[s / PEER_PX_PER_SQUARE, 0, o], [0, s / PEER_PX_PER_SQUARE, o], [0, 0, 1]])  # noqa: N806
    H = intr.K @ np.column_stack([view_T_board[:3, 0], view_T_board[:3, 1], view_T_board[:3, 3]]) @ A  # noqa: N806
    undist = cv2.warpPerspective(texture, H, size, flags=cv2.INTER_LINEAR, borderValue=PEER_BACKGROUND)
    return cv2.remap(undist, maps[0], maps[1], cv2.INTER_LINEAR)


def peer_board_texture(board: BoardSpec) -> np.ndarray:
    m = board.margin_squares
    wb = int(round((board.cols + 1 + 2 * m) * PEER_PX_PER_SQUARE))
    hb = int(round((board.rows + 1 + 2 * m) * PEER_PX_PER_SQUARE))
    yy, xx = np.mgrid[0:hb, 0:wb]
    u = (xx + 0.5) / PEER_PX_PER_SQUARE - (1 + m)
    v = (yy + 0.5) / PEER_PX_PER_SQUARE - (1 + m)
    sq = (u >= -1) & (u < board.cols) & (v >= -1) & (v < board.rows)
    return np.where(sq & ((np.floor(u) + np.floor(v)) % 2 == 0), 30, 220).astype(np.uint8)


def peer_scene_view(scene, intr, size, view_T_ref, maps):  # noqa: N803
    """Quads warped far to near (by centre depth) into the pinhole image, then distorted by remap."""
    R, t = view_T_ref[:3, :3], view_T_ref[:3, 3]  # noqa: N806
    img = np.zeros((size[1], size[0]), np.uint8)
    order = sorted(scene.quads, key=lambda q: -float((R @ q.centre + t)[2]))
    for q in order:
        c, a, b = R @ q.centre + t, R @ q.axis_u, R @ q.axis_v
        th, tw = q.texture.shape
        T = np.array([[2 / tw, 0, 1 / tw - 1], [0, 2 / th, 1 / th - 1], [0, 0, 1]])  # texel -> (s, t)  # noqa: N806
        H = intr.K @ np.column_stack([a, b, c]) @ T  # noqa: N806
        warped = cv2.warpPerspective(q.texture, H, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_TRANSPARENT,
                                     dst=img)
        img = warped
    return cv2.remap(img, maps[0], maps[1], cv2.INTER_LINEAR)


# ---------------------------------------------------------------------------------------------- helpers
def _corner_rms(images, truths) -> tuple[float, int]:
    err = []
    for img, (board, true_px) in zip(images, truths, strict=True):
        c = detect_board(img, board)
        if c is not None:
            err.append(np.sum((c - true_px) ** 2, axis=1))
    return (float(np.sqrt(np.mean(np.concatenate(err)))) if err else float("nan")), len(err)


def _clock() -> tuple[float, float]:
    """(wall, CPU) seconds; CPU counts this process and its finished children (the writers' worker pools)."""
    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.perf_counter(), time.process_time() + ch.ru_utime + ch.ru_stime


def _since(start: tuple[float, float]) -> tuple[float, float]:
    now = _clock()
    return now[0] - start[0], now[1] - start[1]


def _timed(fn, items) -> tuple[list, np.ndarray]:
    """Outputs of ``fn`` over ``items`` and the mean (wall, CPU) seconds per item."""
    out, spent = [], []
    for item in items:
        start = _clock()
        out.append(fn(item))
        spent.append(_since(start))
    return out, np.mean(spent, axis=0)


def _mad(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.mean(np.abs(a.astype(np.float64) - b.astype(np.float64))))


def scene_case(args, rows: list) -> bool:
    named = get_scene("paper-5x5")
    calib = make_rig(named.rig, np.random.default_rng(0))
    near, far = named.scene_depth_m
    cfg = SceneConfig(depth_m=(near, far), background_depth_m=far * 1.4)  # as `lfgraph synth scene`
    quiet = dataclasses.replace(cfg, noise_sigma=0.0)
    size = calib.image_size_px
    views = [int(v) for v in np.linspace(0, calib.num_views - 1, args.old_views).round().astype(int)]
    start = _clock()
    scene = make_scene(cfg, np.random.default_rng([0, 0]))
    scene_spent = np.array(_since(start))
    n = calib.num_views
    # new: the whole frame through the writer (processes, scene generation, PNGs)
    with tempfile.TemporaryDirectory() as tmp:
        start = _clock()
        write_scene_dataset(Path(tmp) / "new", calib, cfg, frames=1, seed=0, jobs=args.jobs, progress=False)
        new_frame = np.array(_since(start))
    # per view, in this process; each renderer in its own loop (interleaving them slows the new one by sharing
    # caches and allocator with the old one's ~1 GB of temporaries); lens rays computed cold for each view
    def new_views(config, rngs):
        sample_rays.cache_clear()
        start = _clock()
        imgs = list(render_scene_views(scene, calib, config, views, rngs))  # as the writer: textures once
        if rngs[0] is not None:
            for img in imgs:
                _encode(img)
        return imgs, np.array(_since(start)) / len(views)

    def old_view(v, config, rng):
        img = render_scene_view_reference(scene, calib.intrinsics[v], size, calib.view_T_ref(v), config, rng)
        if rng is not None:
            _encode(img)
        return img

    def peer_view(v, encode):
        img = peer_scene_view(scene, calib.intrinsics[v], size, calib.view_T_ref(v),
                              _peer_lens_map(calib.intrinsics[v], size))
        if encode:
            _encode(img)
        return img

    render_scene_views(scene, calib, quiet, views[:1])  # warm-up (first calls, allocator), untimed; old runs warm too
    news, new_render = new_views(quiet, [None] * len(views))
    _, new_image = new_views(cfg, [np.random.default_rng([0, 0, v]) for v in views])
    olds, old_render = _timed(lambda v: old_view(v, quiet, None), views)
    _, old_image = _timed(lambda v: old_view(v, cfg, np.random.default_rng([0, 0, v])), views)
    peers, peer_render = _timed(lambda v: peer_view(v, False), views)
    _, peer_image = _timed(lambda v: peer_view(v, True), views)
    depth_err = []
    for v in views:
        intr, T = calib.intrinsics[v], calib.view_T_ref(v)  # noqa: N806
        d_new = render_scene_depth(scene, intr, size, T)
        d_old = render_scene_depth_reference(scene, intr, size, T)
        assert np.array_equal(np.isnan(d_new), np.isnan(d_old))
        depth_err.append(float(np.nanmax(np.abs(d_new - d_old))))
    # the old writer: the new frame with the per-image cost swapped for the old one (wall: spread over jobs), and
    # the scene drawn once per task (parallel: CPU only)
    per_core = np.array([args.jobs, 1])
    parts = min(n, args.jobs)  # tasks the writers split the single frame into
    old_frame = new_frame + (old_image - new_image) * n / per_core + np.array([0.0, (parts - 1) * scene_spent[1]])
    peer_frame = peer_image * n / per_core
    mad = {k: np.mean([_mad(a, b) for a, b in zip(imgs, olds, strict=True)]) for k, imgs in (("new", news),
                                                                                          ("peer", peers))}
    rows += [
        _row("scene paper-5x5, old (ray cast)", n, old_render, old_image, old_frame, old_render, old_frame,
             peer_frame, None, 0.0, f"{len(views)} views, extrap."),
        _row("scene paper-5x5, new", n, new_render, new_image, new_frame, old_render, old_frame, peer_frame, None,
             mad["new"], f"frame: writer; scene drawn in {scene_spent[1]:.2f} s CPU"),
        _row("scene paper-5x5, opencv peer", n, peer_render, peer_image, peer_frame, old_render, old_frame,
             peer_frame, None, mad["peer"], "no AA, painter; extrap."),
    ]
    print(f"scene depth maps: new vs old max |dz| = {max(depth_err):.2e} m (same NaN pattern)")
    return new_frame[0] <= SCENE_FRAME_TARGET_S


def board_set_case(args, rows: list) -> bool:
    named = get_scene("paper-4x4")
    rng = np.random.default_rng(0)
    calib = make_rig(named.rig, rng)
    cfg = named.checkerboard
    truth = make_checkerboard_truth(calib, cfg, rng)
    size = calib.image_size_px
    n_frames, n = cfg.frames, calib.num_views * cfg.frames
    quiet = dataclasses.replace(cfg, noise_sigma=0.0)
    texture = peer_board_texture(cfg.board)
    with tempfile.TemporaryDirectory() as tmp:
        start = _clock()
        write_checkerboard_dataset(Path(tmp) / "new", calib, truth, cfg, seed=0, jobs=args.jobs, progress=False)
        new_set = np.array(_since(start))
        peer_dir = Path(tmp) / "peer"
        peer_dir.mkdir()
        start = _clock()
        for v in range(calib.num_views):
            maps = _peer_lens_map(calib.intrinsics[v], size)
            for f in range(n_frames):
                img = peer_board_view(calib.intrinsics[v], size, calib.view_T_ref(v) @ truth.ref_T_board[f], cfg.board,
                                      maps, texture)
                cv2.imwrite(str(peer_dir / f"{v:02d}_{f:03d}.png"), img)
        peer_set = np.array(_since(start)) / np.array([args.jobs, 1])  # one process; wall as if on --jobs cores
    views = np.linspace(0, calib.num_views - 1, args.old_views).round().astype(int)
    frames = np.linspace(0, n_frames - 1, args.old_frames).round().astype(int)
    pairs = [(int(v), int(f)) for v in views for f in frames]

    def pose(v: int, f: int) -> np.ndarray:
        return calib.view_T_ref(v) @ truth.ref_T_board[f]

    def new_rays(v: int) -> ViewRays:
        sample_rays.cache_clear()
        return ViewRays.compute(calib.intrinsics[v], size)

    def new_image(vf, config, noisy):
        v, f = vf
        img = render_checkerboard_view(calib.intrinsics[v], size, pose(v, f), cfg.board, config,
                                       np.random.default_rng([0, f, v]) if noisy else None, new_rays_of[v])
        return _encode(img, png_params(config)) if noisy else img

    def old_image(vf, config, noisy):
        v, f = vf
        img = render_checkerboard_view_reference(calib.intrinsics[v], size, pose(v, f), cfg.board, config,
                                                 np.random.default_rng([0, f, v]) if noisy else None, old_rays_of[v])
        return _encode(img) if noisy else img

    render_checkerboard_view(calib.intrinsics[0], size, pose(0, 0), cfg.board, quiet)  # warm-up, untimed
    rays, new_rays_spent = _timed(new_rays, views)
    new_rays_of = dict(zip((int(v) for v in views), rays, strict=True))
    new_imgs, new_render = _timed(lambda vf: new_image(vf, quiet, False), pairs)
    _, new_written = _timed(lambda vf: new_image(vf, cfg, True), pairs)
    rays, old_rays_spent = _timed(lambda v: OldViewRays.compute(calib.intrinsics[v], size), views)
    old_rays_of = dict(zip((int(v) for v in views), rays, strict=True))
    old_imgs, old_render = _timed(lambda vf: old_image(vf, quiet, False), pairs)
    _, old_written = _timed(lambda vf: old_image(vf, cfg, True), pairs)
    peer_maps = {int(v): _peer_lens_map(calib.intrinsics[v], size) for v in views}
    imgs = {"old": old_imgs, "new": new_imgs,
            "peer": [peer_board_view(calib.intrinsics[v], size, pose(v, f), cfg.board, peer_maps[v], texture)
                     for v, f in pairs]}
    truths = [(cfg.board, truth.corners_px[v, f]) for v, f in pairs]
    # The old writer differed only in the renderer and the noise: the new set with the per-image and per-view
    # (rays) costs swapped for the old ones (PNG encoding, process start-up and file writing counted as measured).
    per_core = np.array([args.jobs, 1])
    swapped = (old_written - new_written) * n + (old_rays_spent - new_rays_spent) * calib.num_views
    old_set = new_set + swapped / per_core
    rms = {k: _corner_rms(imgs[k], truths)[0] for k in imgs}
    mad = {k: np.mean([_mad(a, b) for a, b in zip(imgs[k], imgs["old"], strict=True)]) for k in ("new", "peer")}
    note = f"{len(views)}x{len(frames)} images"
    rest = new_set[1] - n * new_render[1] - calib.num_views * new_rays_spent[1]
    print(f"board set: besides rendering, the new writer spends {rest:.1f} s CPU ({1e3 * rest / n:.1f} ms per image: "
          f"noise, PNG encoding, files, processes); with a renderer costing nothing the old set would take "
          f"{old_set[1] / rest:.1f}x its CPU time")
    rows += [
        _row("board paper-4x4, old", n, old_render, old_written, old_set, old_render, old_set, peer_set, rms["old"],
             0.0, f"{note}, extrap.; rays {1e3 * old_rays_spent[1]:.0f} ms/view"),
        _row("board paper-4x4, new", n, new_render, new_written, new_set, old_render, old_set, peer_set, rms["new"],
             mad["new"], f"set: writer; rays {1e3 * new_rays_spent[1]:.0f} ms/view"),
        _row("board paper-4x4, opencv peer", n, None, None, peer_set, old_render, old_set, peer_set, rms["peer"],
             mad["peer"], "no AA; 1 process"),
    ]
    return new_set[0] <= BOARD_SET_TARGET_S


def _encode(img: np.ndarray, params: list[int] | None = None) -> np.ndarray:
    """The image as the writers store it (``cv2.imwrite``'s default PNG parameters unless given), in memory."""
    ok, _ = cv2.imencode(".png", img, params or [])
    assert ok
    return img


def _row(case, images, render, written, per_set, old_render, old_set, peer_set, rms, mad, note) -> list:
    """A table row; ``render``, ``written`` (per image), ``per_set`` and the references are (wall, CPU) seconds."""
    def ms(x):
        return (None, None) if x is None else (1e3 * x[0], 1e3 * x[1])

    x_render = None if render is None else old_render[1] / render[1]
    return [case, images, *ms(render), *ms(written), per_set[0], per_set[1], x_render, old_set[0] / per_set[0],
            old_set[1] / per_set[1], peer_set[0] / per_set[0], peer_set[1] / per_set[1], rms, mad, note]


def accuracy_case(rows: list) -> bool:
    """The test's rig: noise-free renders, detected corners vs the true projections."""
    calib = make_rig(RigConfig(rows=2, cols=2, image_size_px=(640, 480), focal_px=600, k1=-0.12, pitch_m=0.01),
                     np.random.default_rng(0))
    cfg = CheckerboardConfig(board=BoardSpec(7, 5, 0.02), frames=6, distance_m=(0.3, 0.6), noise_sigma=0.0)
    truth = make_checkerboard_truth(calib, cfg, np.random.default_rng(1))
    size = calib.image_size_px
    imgs = {"old": [], "new": [], "peer": []}
    truths = []
    for v in range(calib.num_views):
        intr = calib.intrinsics[v]
        rays, maps = OldViewRays.compute(intr, size), _peer_lens_map(intr, size)
        for f in range(cfg.frames):
            T = calib.view_T_ref(v) @ truth.ref_T_board[f]  # noqa: N806
            imgs["old"].append(render_checkerboard_view_reference(intr, size, T, cfg.board, cfg, None, rays))
            imgs["new"].append(render_checkerboard_view(intr, size, T, cfg.board, cfg))
            imgs["peer"].append(peer_board_view(intr, size, T, cfg.board, maps))
            truths.append((cfg.board, truth.corners_px[v, f]))
    rms = {k: _corner_rms(imgs[k], truths) for k in imgs}
    n = len(truths)
    for k, label in (("old", "old"), ("new", "new"), ("peer", "opencv peer")):
        diff = 0.0 if k == "old" else np.mean([_mad(a, b) for a, b in zip(imgs[k], imgs["old"], strict=True)])
        rows.append([f"board test rig, {label}", n, *[None] * 11, rms[k][0], diff, f"{rms[k][1]} boards found"])
    return rms["new"][0] <= CORNER_RMS_LIMIT_PX


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--old-views", type=int, default=3, help="views rendered by the old renderer per case")
    parser.add_argument("--old-frames", type=int, default=3, help="board frames per view for the old renderer")
    args = parser.parse_args(argv)
    rows: list = []
    load_before = os.getloadavg()[0]
    ok_scene = scene_case(args, rows)
    ok_board = board_set_case(args, rows)
    ok_acc = accuracy_case(rows)
    print(f"render benchmark: {args.jobs} jobs on {os.cpu_count()} cores, load average {load_before:.1f} before and "
          f"{os.getloadavg()[0]:.1f} after (wall times suffer above ~{os.cpu_count()}); old renderer extrapolated "
          f"from the images it rendered (see note)")
    print(format_table(["case", "images", "ms_render", "cpu_ms_render", "ms_image", "cpu_ms_image", "s_set",
                        "cpu_s_set", "x_old_render_cpu", "x_old_wall", "x_old_cpu", "x_peer_wall", "x_peer_cpu",
                        "corner_rms_px", "mad_old_grey", "note"], rows, floatfmt=".3g"))
    print(f"targets: scene frame <= {SCENE_FRAME_TARGET_S} s, board set <= {BOARD_SET_TARGET_S} s, "
          f"new corner RMS <= {CORNER_RMS_LIMIT_PX} px (test rig), renderers >= {SPEEDUP_TARGET:.0f}x old")
    missed = [name for name, ok in (("scene frame time", ok_scene), ("board set time", ok_board),
                                    ("corner RMS", ok_acc)) if not ok]
    for row in rows:  # the new renderers' speed-ups in CPU: rendering alone, and as written (PNGs, noise, files)
        if row[0].endswith(", new") and row[8] is not None:
            missed += [f"{row[0]}: {what} {x:.1f}x old" for what, x in (("render", row[8]), ("written", row[10]))
                       if x < SPEEDUP_TARGET]
    print("targets missed: " + ("; ".join(missed) if missed else "none"))
    return 0 if not missed else 1


if __name__ == "__main__":
    sys.exit(main())
