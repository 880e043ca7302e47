"""Textured synthetic scenes for auto-refinement: occluding textured quads ray-cast through each view's lens.

Every pixel is cut into ``supersample x supersample`` sub-pixels whose centres are undistorted through the view's
lens (`Intrinsics.undistort`), intersected with every quad (a z-buffer keeps the nearest), and the quad's texture is
sampled bilinearly (`cv2.remap`); the sub-pixels are averaged. Textures follow a "dead leaves" model — overlapping
rectangles, discs and triangles of random grey at many scales — which has natural-image statistics and plenty of
corners for Shi–Tomasi + KLT. The "keyboard" scene is the paper's hard case: one repeated key cap.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from lfgraph.calibration import Calibration
from lfgraph.camera import Intrinsics
from lfgraph.capture import write_frame
from lfgraph.geometry import rotation_from_rotvec
from lfgraph.parallel import run_tasks


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


def _bilinear(texture: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear texture lookup at texel coordinates (x, y), edges replicated."""
    th, tw = texture.shape
    x = np.clip(x, 0, tw - 1)
    y = np.clip(y, 0, th - 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), tw - 2)
    y0 = np.minimum(np.floor(y).astype(np.int64), th - 2)
    fx, fy = x - x0, y - y0
    t = texture.astype(np.float32)
    top = t[y0, x0] * (1 - fx) + t[y0, x0 + 1] * fx
    bottom = t[y0 + 1, x0] * (1 - fx) + t[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bottom * fy


def _cast(scene: Scene, view_T_ref: np.ndarray, xy: np.ndarray, want_texture: bool):  # noqa: N803
    """Ray-cast normalised rays ``xy`` (N, 2) of a view: returns depth (N,) and grey level (N,) (NaN: no hit)."""
    n = xy.shape[0]
    depth = np.full(n, np.inf)
    grey = np.full(n, np.nan)
    d = np.column_stack([xy, np.ones(n)])
    R, t = view_T_ref[:3, :3], view_T_ref[:3, 3]  # noqa: N806
    for q in scene.quads:
        c = R @ q.centre + t
        a, b = R @ q.axis_u, R @ q.axis_v
        normal = np.cross(a, b)
        denom = d @ normal
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = (c @ normal) / denom  # ray parameter = depth, as d_z = 1
            p = d * lam[:, None] - c
            s = (p @ a) / (a @ a)
            u = (p @ b) / (b @ b)
            hit = (lam > 0) & (np.abs(s) <= 1) & (np.abs(u) <= 1) & (lam < depth)
        if not np.any(hit):
            continue
        depth[hit] = lam[hit]
        if want_texture:
            th, tw = q.texture.shape
            mx = (s[hit] + 1) / 2 * tw - 0.5  # texel centres at (k + 0.5) / tw
            my = (u[hit] + 1) / 2 * th - 0.5
            grey[hit] = _bilinear(q.texture, mx, my)
    depth[~np.isfinite(depth)] = np.nan
    return depth, grey


def render_scene_depth(scene: Scene, intrinsics: Intrinsics, image_size_px: tuple[int, int],
                       view_T_ref: np.ndarray) -> np.ndarray:  # noqa: N803
    """(H, W) depth (z in the view frame, metres) at pixel centres; NaN where no surface is hit."""
    w, h = image_size_px
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    xy = intrinsics.undistort(np.column_stack([u.ravel(), v.ravel()]))
    depth, _ = _cast(scene, view_T_ref, xy, want_texture=False)
    return depth.reshape(h, w)


def render_scene_view(scene: Scene, intrinsics: Intrinsics, image_size_px: tuple[int, int], view_T_ref: np.ndarray,  # noqa: N803
                      config: SceneConfig, rng: np.random.Generator | None = None) -> np.ndarray:
    """Render one view as (H, W) uint8, supersampled; blur and noise per ``config`` (noise only with ``rng``)."""
    w, h = image_size_px
    n = config.supersample
    offsets = (np.arange(n) + 0.5) / n - 0.5
    u = (np.arange(w)[None, :, None, None] + offsets[None, None, None, :]) + 0 * offsets[None, None, :, None]
    v = (np.arange(h)[:, None, None, None] + offsets[None, None, :, None]) + 0 * offsets[None, None, None, :]
    u, v = np.broadcast_arrays(u, v)
    xy = intrinsics.undistort(np.column_stack([u.ravel(), v.ravel()]))
    _, grey = _cast(scene, view_T_ref, xy, want_texture=True)
    grey = np.nan_to_num(grey, nan=0.0).reshape(h, w, n * n).mean(axis=2)
    if config.blur_sigma_px > 0:
        grey = cv2.GaussianBlur(grey, (0, 0), config.blur_sigma_px)
    if rng is not None and config.noise_sigma > 0:
        grey = grey + config.noise_sigma * rng.standard_normal(grey.shape)
    return np.clip(np.rint(grey), 0, 255).astype(np.uint8)


def _render_frame_task(args: tuple) -> int:
    calib_json, config, seed, frame, out_dir, layout = args
    calib = Calibration.from_dict(json.loads(calib_json))
    scene = make_scene(config, np.random.default_rng([seed, frame]))
    images = np.stack([
        render_scene_view(scene, calib.intrinsics[v], calib.image_size_px, calib.view_T_ref(v), config,
                          np.random.default_rng([seed, frame, v]))
        for v in range(calib.num_views)])
    write_frame(out_dir, f"{frame:03d}", images, calib.grid, layout=layout)
    return frame


def write_scene_dataset(out_dir: str | os.PathLike, calib: Calibration, config: SceneConfig, frames: int, seed: int,
                        layout: str = "folders", jobs: int | None = None, progress: bool = True,
                        original: Calibration | None = None) -> None:
    """Render ``frames`` random scenes seen by ``calib`` to ``out_dir`` with ``truth.json`` (and ``original.json``).

    Frame f's scene is drawn from (seed, f) and its noise from (seed, f, view), so any ``jobs`` gives the same files.
    """
    if layout not in ("folders", "mosaic"):
        raise ValueError(f"layout must be 'folders' or 'mosaic', got {layout!r}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tasks = [(calib.to_json(), config, seed, f, str(out), layout) for f in range(frames)]
    run_tasks(_render_frame_task, tasks, jobs, "rendering frames", "frame", progress)
    calib.save(out / "truth.json")
    if original is not None:
        original.save(out / "original.json")
