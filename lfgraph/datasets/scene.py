"""Textured synthetic scenes for auto-refinement: occluding textured quads ray-cast through each view's lens.

Every pixel is cut into ``supersample x supersample`` sub-pixels whose centres are undistorted through the view's
lens (cached per lens, `lfgraph.datasets.render.sample_rays`). Each quad maps those rays to its texels by a
homography and its inverse depth is affine in them, so per quad, over the window of samples that can see it,
OpenCV computes texel coordinates (`cv2.perspectiveTransform`), inverse depth (`cv2.transform`) and the bilinear
texture value (`cv2.remap`); a per-sample z-buffer keeps the nearest quad (exact also for intersecting quads). The
sub-pixels are averaged (`cv2.resize`, INTER_AREA). These are the samples of casting every ray against every quad
(`cv2.remap` places them to 1/32 texel), at ~1/20 of the CPU time. Textures follow a "dead leaves" model —
overlapping rectangles, discs and triangles of random grey at many scales — which has natural-image statistics and
plenty of corners for Shi–Tomasi + KLT. The "keyboard" scene is the paper's hard case: one repeated key cap.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.camera import Intrinsics
from lfgraph.core.files import atomic_path
from lfgraph.core.geometry import rotation_from_rotvec
from lfgraph.core.parallel import run_tasks
from lfgraph.datasets.render import (
    NEAR_PLANE_M,
    LensRays,
    clip_polygon_near,
    cross3,
    plane_maps,
    sample_rays,
    to_uint8,
)
from lfgraph.io.capture import write_frame

PLANE_EDGE_ON_M3 = 1e-12  # |normal . centre| below this (axes in metres): the camera lies in the quad's plane


@dataclass(frozen=True)
class SceneConfig:
    """A random scene in front of the array.

    Attributes:
        depth_m: (near, far) depth range of the objects, metres from the reference view.
        objects: number of textured planes and boxes.
        box_fraction: share of the objects that are boxes (front, side and top faces).
        background_depth_m: depth of the textured background plane that fills every view.
        texels_per_m_at_1m: texture resolution scale; a quad at depth z gets about this / z texels per metre.
        supersample: N for N x N sub-pixel rays per pixel.
        blur_sigma_px: Gaussian blur after rendering (0 = none).
        noise_sigma: sensor noise, grey levels std (0 = none).
        kind: ``"dead-leaves"`` (natural texture) or ``"keyboard"`` (repetitive key caps).
    """

    depth_m: tuple[float, float] = (2.0, 6.0)
    objects: int = 8
    box_fraction: float = 0.4
    background_depth_m: float = 8.0
    texels_per_m_at_1m: float = 700.0
    supersample: int = 2
    blur_sigma_px: float = 0.5
    noise_sigma: float = 1.0
    kind: str = "dead-leaves"

    def __post_init__(self) -> None:
        near, far = self.depth_m
        if not (0 < near <= far < self.background_depth_m):
            raise ValueError(f"need 0 < near <= far < background depth, got {self.depth_m} and "
                             f"{self.background_depth_m}")
        if self.kind not in ("dead-leaves", "keyboard"):
            raise ValueError(f"scene kind must be 'dead-leaves' or 'keyboard', got {self.kind!r}")


@dataclass(frozen=True)
class TexturedQuad:
    """A flat textured rectangle: points ``centre + s * axis_u + t * axis_v`` for s, t in [-1, 1] (reference frame).

    The texture's column grows with s, its row with t.
    """

    centre: np.ndarray  # (3,) metres
    axis_u: np.ndarray  # (3,) half edge, metres
    axis_v: np.ndarray  # (3,) half edge, metres
    texture: np.ndarray  # (h, w) uint8


@dataclass(frozen=True)
class Scene:
    """A random scene: textured planar quads (the background plane, then the objects' faces), in the reference view's
    frame (m)."""
    quads: tuple[TexturedQuad, ...]


def dead_leaves_texture(size: tuple[int, int], rng: np.random.Generator, shapes: int | None = None) -> np.ndarray:
    """(h, w) uint8 dead-leaves texture: overlapping shapes of random grey, sizes spread over scales."""
    w, h = size
    img = np.full((h, w), rng.uniform(60, 200), dtype=np.float32)
    n = shapes or int(40 + w * h / 400)
    scale = max(w, h)
    for _ in range(n):
        r = scale * np.exp(rng.uniform(np.log(0.006), np.log(0.12)))  # many small, few large
        x, y = rng.uniform(-0.05, 1.05) * w, rng.uniform(-0.05, 1.05) * h
        grey = float(rng.uniform(10, 245))
        kind = rng.integers(3)
        if kind == 0:
            ang = rng.uniform(0, 180)
            box = cv2.boxPoints(((x, y), (2 * r, 2 * r * rng.uniform(0.3, 1.0)), ang))
            cv2.fillConvexPoly(img, np.round(box * 16).astype(np.int32), grey, cv2.LINE_AA, 4)
        elif kind == 1:
            cv2.circle(img, (int(x * 16), int(y * 16)), int(r * 16), grey, -1, cv2.LINE_AA, 4)
        else:
            pts = np.array([x, y]) + r * rng.uniform(-1, 1, (3, 2))
            cv2.fillConvexPoly(img, np.round(pts * 16).astype(np.int32), grey, cv2.LINE_AA, 4)
    return np.clip(img, 0, 255).astype(np.uint8)


def keyboard_texture(size: tuple[int, int], key_px: int = 24) -> np.ndarray:
    """(h, w) uint8 grid of identical key caps with one repeated glyph: a strongly periodic texture."""
    w, h = size
    tile = np.full((key_px, key_px), 40, dtype=np.uint8)
    m = max(2, key_px // 8)
    cv2.rectangle(tile, (m, m), (key_px - 1 - m, key_px - 1 - m), 200, -1)
    cv2.line(tile, (key_px // 3, key_px // 3), (2 * key_px // 3, 2 * key_px // 3), 60, max(1, key_px // 12))
    reps = (h // key_px + 1, w // key_px + 1)
    return np.tile(tile, reps)[:h, :w].copy()


def _texture_for(cfg: SceneConfig, width_m: float, height_m: float, depth_m: float, rng: np.random.Generator,
                 keyboard: bool = False) -> np.ndarray:
    density = cfg.texels_per_m_at_1m / depth_m
    size = (int(np.clip(width_m * density, 16, 2048)), int(np.clip(height_m * density, 16, 2048)))
    return keyboard_texture(size) if keyboard else dead_leaves_texture(size, rng)


def _quad(centre, R, half_w, half_h, texture) -> TexturedQuad:  # noqa: N803
    return TexturedQuad(np.asarray(centre, float), R[:, 0] * half_w, R[:, 1] * half_h, texture)


def make_scene(config: SceneConfig, rng: np.random.Generator) -> Scene:
    """Random occluding planes and boxes at ``config.depth_m`` in front of a background plane. Seeded and pure."""
    quads = []
    zb = config.background_depth_m
    bg = 1.6 * zb  # half size: wide enough for 5x5 rigs with 100 mm pitch and ~60 degree views
    quads.append(_quad([0.0, 0.0, zb], np.eye(3), bg, bg,
                       _texture_for(config, 2 * bg, 2 * bg, zb, rng, keyboard=config.kind == "keyboard")))
    near, far = config.depth_m
    for i in range(config.objects):
        z = rng.uniform(near, far)
        x, y = rng.uniform(-0.45, 0.45, 2) * z  # inside a ~50 degree cone of the reference view
        half = rng.uniform(0.08, 0.22) * z
        R = rotation_from_rotvec(np.radians(rng.uniform(-25, 25, 3)) * [1, 1, 0.5])  # noqa: N806
        keyboard = config.kind == "keyboard" and i == 0
        if rng.uniform() < config.box_fraction and not keyboard:
            d = half * rng.uniform(0.5, 1.0)  # box depth
            front = np.array([x, y, z])
            quads.append(_quad(front, R, half, half, _texture_for(config, 2 * half, 2 * half, z, rng)))
            # side (+x) and top (-y) faces, extending away from the viewer
            side_c = front + R[:, 0] * half + R[:, 2] * d
            side_R = R @ rotation_from_rotvec([0, np.pi / 2, 0])  # noqa: N806
            quads.append(_quad(side_c, side_R, d, half, _texture_for(config, 2 * d, 2 * half, z, rng)))
            top_c = front - R[:, 1] * half + R[:, 2] * d
            top_R = R @ rotation_from_rotvec([np.pi / 2, 0, 0])  # noqa: N806
            quads.append(_quad(top_c, top_R, half, d, _texture_for(config, 2 * half, 2 * d, z, rng)))
        else:
            quads.append(_quad([x, y, z], R, half * 1.3, half,
                               _texture_for(config, 2.6 * half, 2 * half, z, rng, keyboard=keyboard)))
    return Scene(tuple(quads))


@dataclass(frozen=True, eq=False)
class _PreparedQuad:
    """A quad in one view's frame, ready for sampling: float32 texture and the maps of its plane."""

    texel_H: np.ndarray  # (3, 3) normalised image coordinates -> texel coordinates (column, row)
    inv_depth: np.ndarray  # (1, 3) inverse depth as an affine function of normalised coordinates
    corners_xy: np.ndarray  # (k, 2) normalised coordinates of its (near-clipped) outline, for the sample window
    texture: np.ndarray  # (h, w) float32
    texel_max: tuple[float, float]  # last texel column and row covered: (w - 0.5, h - 0.5)
    behind_all: bool  # wholly in front of the camera and behind every other quad along every ray (see `_prepare`)


def _prepare(scene: Scene, view_T_ref: np.ndarray, textures: list[np.ndarray] | None) -> list[_PreparedQuad]:  # noqa: N803
    """The quads in the view's frame, without those seen edge-on or wholly behind the camera.

    A quad is ``behind_all`` when it lies wholly in front of the camera and every corner of every other quad lies
    strictly on the camera's side of its plane: then (the quads being convex) any ray meets every other quad
    before its plane, so it only shows where nothing else does (the background, as a rule).
    """
    R, t = view_T_ref[:3, :3], view_T_ref[:3, 3]  # noqa: N806
    placed = [(R @ q.centre + t, R @ q.axis_u, R @ q.axis_v) for q in scene.quads]
    corners = [np.array([c - a - b, c + a - b, c + a + b, c - a + b]) for c, a, b in placed]
    out = []
    for i, q in enumerate(scene.quads):
        c, a, b = placed[i]
        normal = cross3(a, b)
        if abs(float(np.sum(normal * c))) < PLANE_EDGE_ON_M3:
            continue  # the plane contains the camera centre: seen edge-on, it covers no area
        outline = clip_polygon_near(corners[i])
        if len(outline) == 0:
            continue
        camera_side = -float(np.sum(normal * c))  # sign of normal . (camera - c)
        others = np.concatenate([corners[j] for j in range(len(corners)) if j != i] or [np.zeros((0, 3))])
        behind_all = bool(np.all(corners[i][:, 2] >= NEAR_PLANE_M)
                          and np.all(np.sum((others - c) * normal, axis=1) * camera_side > 0))
        st_H, inv_depth = plane_maps(c, a, b)  # noqa: N806
        th, tw = q.texture.shape
        # texel centres at (k + 0.5) / w of the [-1, 1] range: column = (s + 1) / 2 * w - 0.5 (written out rather
        # than a matrix product, whose BLAS rounding may depend on the thread count)
        texel_H = np.stack([tw / 2 * st_H[0] + (tw / 2 - 0.5) * st_H[2], th / 2 * st_H[1] + (th / 2 - 0.5) * st_H[2],  # noqa: N806
                            st_H[2]])
        texture = textures[i] if textures is not None else q.texture.astype(np.float32)
        out.append(_PreparedQuad(texel_H, inv_depth, outline[:, :2] / outline[:, 2:], texture, (tw - 0.5, th - 0.5),
                                 behind_all))
    return out


def _sample(quads: list[_PreparedQuad], rays: LensRays, want_texture: bool,
            exact: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
    """Point-sample the scene along every ray of ``rays``: inverse depth (0 = no hit) and grey level (0 = no hit).

    Per quad, only the window of samples that can see it is processed: texel coordinates by the quad's homography
    (`cv2.perspectiveTransform`), inverse depth by an affine map (`cv2.transform`), the texture by bilinear
    `cv2.remap` with edges replicated; a sample takes the quad when it lies inside the quad's outline and is nearer
    than what it holds (a per-sample z-buffer, exact for intersecting quads). ``exact`` works in float64.

    For the grey level alone, quads behind all others (`_PreparedQuad.behind_all`) are drawn last and only where
    no other quad was hit, without their inverse depth (which then stays 0 there).
    """
    xy = rays.xy if exact else rays.xy32
    inv_z = np.zeros(xy.shape[:2], dtype=xy.dtype)
    grey = np.zeros(xy.shape[:2], dtype=np.float32) if want_texture else None
    last = [q for q in quads if q.behind_all] if want_texture and not exact else []
    for q in quads:
        if q.behind_all and last:
            continue  # drawn below
        window = rays.roi(q.corners_xy)
        if window is None:
            continue
        sub = xy[window]
        texel = cv2.perspectiveTransform(sub, q.texel_H)
        w = cv2.transform(sub, q.inv_depth)
        nearer = np.greater(w, inv_z[window])  # NaN rays (beyond the lens fold) compare False
        nearer &= cv2.inRange(texel, (-0.5, -0.5), q.texel_max) > 0
        if not nearer.any():
            continue
        np.copyto(inv_z[window], w, where=nearer)  # in place, no gather and scatter of the samples (~2x faster)
        if want_texture:
            texel32 = texel if texel.dtype == np.float32 else texel.astype(np.float32)
            values = cv2.remap(q.texture, texel32, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            np.copyto(grey[window], values, where=nearer)
    for q in last:  # behind every other quad: a sample shows it only where no other quad was hit
        window = rays.roi(q.corners_xy)
        if window is None:
            continue
        texel = cv2.perspectiveTransform(xy[window], q.texel_H)
        empty = np.equal(inv_z[window], 0)
        empty &= cv2.inRange(texel, (-0.5, -0.5), q.texel_max) > 0
        values = cv2.remap(q.texture, texel, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        np.copyto(grey[window], values, where=empty)
    return inv_z, grey


def render_scene_depth(scene: Scene, intrinsics: Intrinsics, image_size_px: tuple[int, int],
                       view_T_ref: np.ndarray) -> np.ndarray:  # noqa: N803
    """(H, W) depth (z in the view frame, metres) at pixel centres; NaN where no surface is hit.

    Exact: float64 rays through the pixel centres, the nearest quad per ray, z from its plane equation.
    """
    inv_z, _ = _sample(_prepare(scene, view_T_ref, None), sample_rays(intrinsics, tuple(image_size_px), 1),
                       want_texture=False, exact=True)
    with np.errstate(divide="ignore"):
        return np.where(inv_z > 0, 1.0 / inv_z, np.nan)


def render_scene_view(scene: Scene, intrinsics: Intrinsics, image_size_px: tuple[int, int], view_T_ref: np.ndarray,  # noqa: N803
                      config: SceneConfig, rng: np.random.Generator | None = None) -> np.ndarray:
    """Render one view as (H, W) uint8, supersampled; blur and noise per ``config`` (noise only with ``rng``)."""
    return _render_view(scene, None, intrinsics, image_size_px, view_T_ref, config, rng)


def render_scene_views(scene: Scene, calib: Calibration, config: SceneConfig, views: list[int] | None = None,
                       rngs: list[np.random.Generator | None] | None = None) -> np.ndarray:
    """(len(views), H, W) uint8: `render_scene_view` for several views of one scene, textures prepared once (a list
    of (H, W) images when the views differ in size).

    Args:
        scene: the scene.
        calib: the array (intrinsics and poses of the views).
        config: supersampling, blur, noise.
        views: view indices (default: all).
        rngs: one noise source per view (None entries or None: no noise).
    """
    views = list(range(calib.num_views)) if views is None else list(views)
    rngs = [None] * len(views) if rngs is None else list(rngs)
    if len(rngs) != len(views):
        raise ValueError(f"need one rng per view, got {len(rngs)} for {len(views)} views")
    textures = [q.texture.astype(np.float32) for q in scene.quads]
    out = [_render_view(scene, textures, calib.intrinsics[v], calib.image_size(v), calib.view_T_ref(v), config, rng)
           for v, rng in zip(views, rngs, strict=True)]
    return out if len({img.shape for img in out}) > 1 else np.stack(out)


def _render_view(scene: Scene, textures: list[np.ndarray] | None, intrinsics: Intrinsics,
                 image_size_px: tuple[int, int], view_T_ref: np.ndarray, config: SceneConfig,  # noqa: N803
                 rng: np.random.Generator | None) -> np.ndarray:
    w, h = image_size_px
    rays = sample_rays(intrinsics, (int(w), int(h)), config.supersample)
    _, grey = _sample(_prepare(scene, view_T_ref, textures), rays, want_texture=True)
    # integer-factor INTER_AREA is the exact mean of each pixel's n x n samples
    grey = cv2.resize(grey, (w, h), interpolation=cv2.INTER_AREA) if config.supersample > 1 else grey
    if config.blur_sigma_px > 0:
        grey = cv2.GaussianBlur(grey, (0, 0), config.blur_sigma_px)
    return to_uint8(grey, config.noise_sigma, rng)


def _render_frame_task(args: tuple) -> int:
    """Render views ``views`` of one frame; all of them go through ``write_frame`` in ``layout``, a part of them
    is written as one PNG per view (``folders``) for the parent to assemble. The frame's scene comes with the task
    when the parent drew it (a frame split over several tasks), else it is drawn here."""
    calib_json, config, seed, frame, views, out_dir, layout, scene = args
    calib = Calibration.from_dict(json.loads(calib_json))
    if scene is None:
        scene = make_scene(config, np.random.default_rng([seed, frame]))
    images = render_scene_views(scene, calib, config, views, [np.random.default_rng([seed, frame, v]) for v in views])
    if len(views) == calib.num_views:
        write_frame(out_dir, f"{frame:03d}", images, calib.grid, layout=layout)
        return frame
    for v, img in zip(views, images, strict=True):
        path = Path(out_dir) / f"{frame:03d}" / f"{calib.grid.name(v)}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            if not cv2.imwrite(str(tmp), img):
                raise OSError(f"could not write {path}")
    return frame


def write_scene_dataset(out_dir: str | os.PathLike, calib: Calibration, config: SceneConfig, frames: int, seed: int,
                        layout: str = "folders", jobs: int | None = None, progress: bool = True,
                        original: Calibration | None = None) -> None:
    """Render ``frames`` random scenes seen by ``calib`` to ``out_dir`` with ``truth.json`` (and ``original.json``).

    One task per frame; with fewer frames than ``jobs``, each frame's views are split over several tasks so that
    every process has work (the frame's scene is then drawn once, here, and sent to them). Frame f's scene is drawn
    from (seed, f) and its noise from (seed, f, view), so any ``jobs`` gives the same files.
    """
    if layout not in ("folders", "mosaic"):
        raise ValueError(f"layout must be 'folders' or 'mosaic', got {layout!r}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    n_jobs = max(1, jobs or os.cpu_count() or 1)
    parts = min(calib.num_views, -(-n_jobs // max(frames, 1)))
    views = [list(c) for c in np.array_split(np.arange(calib.num_views), parts)]
    render_dir = out if parts == 1 or layout == "folders" else Path(tempfile.mkdtemp(prefix=".render-", dir=out))
    scenes = [make_scene(config, np.random.default_rng([seed, f])) if parts > 1 else None for f in range(frames)]
    tasks = [(calib.to_json(), config, seed, f, [int(v) for v in vs], str(render_dir), layout, scenes[f])
             for f in range(frames) for vs in views]
    try:
        run_tasks(_render_frame_task, tasks, jobs, "rendering frames", "frame", progress)
        if render_dir != out:
            for f in range(frames):
                images = np.stack([cv2.imread(str(render_dir / f"{f:03d}" / f"{calib.grid.name(v)}.png"),
                                              cv2.IMREAD_GRAYSCALE) for v in range(calib.num_views)])
                write_frame(out, f"{f:03d}", images, calib.grid, layout=layout)
    finally:
        if render_dir != out:
            shutil.rmtree(render_dir, ignore_errors=True)
    calib.save(out / "truth.json")
    if original is not None:
        original.save(out / "original.json")
