"""Textured scenes: features land where geometry says, occlusion is right, KLT can track the texture."""

import cv2
import numpy as np
import pytest

from lfgraph.core.geometry import rotation_from_rotvec
from lfgraph.datasets.rig import RigConfig, make_rig
from lfgraph.datasets.scene import (
    Scene,
    SceneConfig,
    TexturedQuad,
    keyboard_texture,
    make_scene,
    render_scene_depth,
    render_scene_view,
    write_scene_dataset,
)

FEATURE_POSITION_LIMIT_PX = 0.05  # rendered X-corner vs projection of its 3-D point
DEPTH_EXACT_M = 1e-9
KLT_MEDIAN_LIMIT_PX = 0.2
KLT_TRACKED_SHARE = 0.8
MIN_FEATURES = 300


def _rig(rows=2, cols=2, size=(320, 240), f=300.0, pitch=0.05):
    return make_rig(RigConfig(rows=rows, cols=cols, image_size_px=size, focal_px=f, pitch_m=pitch, k1=-0.1),
                    np.random.default_rng(0))


def _x_corner_scene(centre, R):  # noqa: N803
    tex = np.full((64, 64), 220, np.uint8)
    tex[:32, :32] = 30
    tex[32:, 32:] = 30
    return Scene((TexturedQuad(np.asarray(centre), R[:, 0] * 0.3, R[:, 1] * 0.3, tex),))


def test_rendered_corner_lands_at_its_projection():
    calib = _rig()
    centre = np.array([0.05, -0.03, 1.5])
    scene = _x_corner_scene(centre, rotation_from_rotvec([0.3, -0.2, 0.4]))
    cfg = SceneConfig(supersample=4, blur_sigma_px=0.8, noise_sigma=0.0)
    errors = []
    for v in range(calib.num_views):
        img = render_scene_view(scene, calib.intrinsics[v], calib.image_size_px, calib.view_T_ref(v), cfg)
        view_T_ref = calib.view_T_ref(v)  # noqa: N806
        truth = calib.intrinsics[v].project((view_T_ref[:3, :3] @ centre + view_T_ref[:3, 3])[None])[0]
        start = (truth + [1.5, -1.2]).astype(np.float32).reshape(1, 1, 2)
        cv2.cornerSubPix(img, start, (6, 6), (-1, -1), (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-5))
        errors.append(np.linalg.norm(start.ravel() - truth))
    assert max(errors) <= FEATURE_POSITION_LIMIT_PX, errors


def test_occlusion_and_exact_depth():
    calib = _rig()
    tex = np.full((8, 8), 100, np.uint8)
    far = TexturedQuad(np.array([0, 0, 3.0]), np.array([2.0, 0, 0]), np.array([0, 2.0, 0]), tex)
    near = TexturedQuad(np.array([0, 0, 1.0]), np.array([0.1, 0, 0]), np.array([0, 0.1, 0]), tex)
    depth = render_scene_depth(Scene((far, near)), calib.intrinsics[0], calib.image_size_px, np.eye(4))
    intr = calib.intrinsics[0]
    centre_px = np.round(intr.project(np.array([[0.0, 0.0, 1.0]]))[0]).astype(int)
    assert abs(depth[centre_px[1], centre_px[0]] - 1.0) < DEPTH_EXACT_M  # the near quad hides the far one
    assert abs(depth[5, 5] - 3.0) < DEPTH_EXACT_M  # fronto-parallel plane: z is constant


@pytest.fixture(scope="module")
def paper_like():
    # paper-5x5-like: 512x512, f = 700 px, 100 mm pitch, objects at 2-6 m
    calib = make_rig(RigConfig(rows=1, cols=2, image_size_px=(512, 512), focal_px=700, pitch_m=0.1, k1=-0.05,
                               k2=0.01), np.random.default_rng(2))
    cfg = SceneConfig()
    scene = make_scene(cfg, np.random.default_rng(1))
    imgs = [render_scene_view(scene, calib.intrinsics[v], (512, 512), calib.view_T_ref(v), cfg,
                              np.random.default_rng(v)) for v in range(2)]
    depth = render_scene_depth(scene, calib.intrinsics[0], (512, 512), calib.view_T_ref(0))
    return calib, imgs, depth


def test_texture_has_trackable_corners_everywhere(paper_like):
    calib, (a, b), depth = paper_like
    pts = cv2.goodFeaturesToTrack(a, 2000, 0.01, 5).reshape(-1, 2)
    assert len(pts) >= MIN_FEATURES
    cells = {(int(x // 128), int(y // 128)) for x, y in pts}
    assert len(cells) >= 14  # of 16
    nxt, status, _ = cv2.calcOpticalFlowPyrLK(a, b, pts.astype(np.float32).reshape(-1, 1, 2), None,
                                              winSize=(15, 15), maxLevel=3)
    ok = status.ravel().astype(bool)
    assert ok.mean() >= KLT_TRACKED_SHARE
    # ground truth correspondence: back-project through the depth map, project into the neighbour
    ij = np.round(pts).astype(int)
    z = depth[ij[:, 1], ij[:, 0]]
    xy = calib.intrinsics[0].undistort(pts)
    p_ref = np.column_stack([xy * z[:, None], z])
    view_T_ref = calib.view_T_ref(1)  # noqa: N806
    truth = calib.intrinsics[1].project(p_ref @ view_T_ref[:3, :3].T + view_T_ref[:3, 3])
    err = np.linalg.norm(nxt.reshape(-1, 2) - truth, axis=1)
    assert np.nanmedian(err[ok]) <= KLT_MEDIAN_LIMIT_PX


def test_keyboard_is_periodic():
    key = 24
    tex = keyboard_texture((240, 120), key_px=key).astype(float)
    row = tex[key // 2]

    def corr(lag: int) -> float:
        return float(np.corrcoef(row[:-lag], row[lag:])[0, 1])

    assert corr(key) > 0.99 and corr(key // 4) < 0  # repeats every key; a quarter key off it anti-correlates


def test_scene_dataset_is_seeded_and_job_independent(tmp_path):
    calib = _rig(size=(96, 64), f=90.0)
    cfg = SceneConfig(objects=3, texels_per_m_at_1m=200)
    write_scene_dataset(tmp_path / "a", calib, cfg, frames=2, seed=1, jobs=1, progress=False, original=calib)
    write_scene_dataset(tmp_path / "b", calib, cfg, frames=2, seed=1, jobs=2, progress=False)
    for name in ("000/r00_c00.png", "001/r01_c01.png"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
    assert (tmp_path / "a" / "original.json").exists() and not (tmp_path / "b" / "original.json").exists()
    write_scene_dataset(tmp_path / "m", calib, cfg, frames=1, seed=1, layout="mosaic", jobs=1, progress=False)
    assert cv2.imread(str(tmp_path / "m" / "000.png"), 0).shape == (128, 192)
    # one frame on 2 jobs: its views are split over two tasks, same files
    write_scene_dataset(tmp_path / "s", calib, cfg, frames=1, seed=1, jobs=2, progress=False)
    write_scene_dataset(tmp_path / "sm", calib, cfg, frames=1, seed=1, layout="mosaic", jobs=2, progress=False)
    for name in ("000/r00_c00.png", "000/r01_c01.png"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "s" / name).read_bytes()
    assert (tmp_path / "m" / "000.png").read_bytes() == (tmp_path / "sm" / "000.png").read_bytes()
    assert sorted(p.name for p in (tmp_path / "sm").iterdir()) == ["000.png", "truth.json"]
    with pytest.raises(ValueError, match="scene kind"):
        SceneConfig(kind="forest")


RAY_ROUND_TRIP_LIMIT_PX = {1: 1e-6, 2: 1e-3}  # float64 pixel centres; float32 supersampled grid


@pytest.mark.parametrize("supersample", [1, 2])
def test_cached_lens_rays_project_back_onto_their_samples(supersample):
    from lfgraph.core.camera import Intrinsics
    from lfgraph.datasets.render import sample_rays

    intr = Intrinsics(300.0, 310.0, 161.0, 118.0, k1=-0.15, k2=0.02, p1=1e-3, p2=-2e-3)
    w, h, n = 320, 240, supersample
    rays = sample_rays(intr, (w, h), n)
    assert rays.xy.shape == (h * n, w * n, 2)
    rows, cols = np.meshgrid(np.arange(h * n), np.arange(w * n), indexing="ij")
    sample_px = np.column_stack([(cols.ravel() + 0.5) / n - 0.5, (rows.ravel() + 0.5) / n - 0.5])
    # the forward lens model is the ground truth: projecting each ray must land on its sample
    back = intr.project(rays.xy.reshape(-1, 2).astype(np.float64))
    assert np.max(np.abs(back - sample_px)) <= RAY_ROUND_TRIP_LIMIT_PX[n]


def test_intersecting_quads_keep_the_nearer_surface_per_pixel():
    """Two planes crossing each other (painter's order cannot draw them): depth is the nearer plane everywhere."""
    calib = _rig()
    intr = calib.intrinsics[0]
    tex = np.full((8, 8), 100, np.uint8)
    # z = 2 + X / 2 and z = 2 - X / 2, both wider than the view
    a = TexturedQuad(np.array([0.0, 0, 2.0]), np.array([2.0, 0, 1.0]), np.array([0, 2.0, 0]), tex)
    b = TexturedQuad(np.array([0.0, 0, 2.0]), np.array([2.0, 0, -1.0]), np.array([0, 2.0, 0]), tex)
    depth = render_scene_depth(Scene((a, b)), intr, calib.image_size_px, np.eye(4))
    w, h = calib.image_size_px
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    xy = intr.undistort(np.column_stack([u.ravel(), v.ravel()]))
    x = xy[:, 0]
    # ray (x, y, 1) meets z = 2 + k X with X = x z: z = 2 / (1 - k x)
    truth = np.minimum(2.0 / (1.0 - 0.5 * x), 2.0 / (1.0 + 0.5 * x)).reshape(h, w)
    assert not np.isnan(depth).any()
    assert np.max(np.abs(depth - truth)) < DEPTH_EXACT_M


def test_rendering_several_views_at_once_matches_one_by_one():
    from lfgraph.datasets.scene import render_scene_views

    calib = _rig(size=(96, 64), f=90.0)
    cfg = SceneConfig(objects=3, texels_per_m_at_1m=200)
    scene = make_scene(cfg, np.random.default_rng(4))
    many = render_scene_views(scene, calib, cfg, [3, 1], [np.random.default_rng(3), np.random.default_rng(1)])
    for img, v in zip(many, [3, 1], strict=True):
        one = render_scene_view(scene, calib.intrinsics[v], calib.image_size_px, calib.view_T_ref(v), cfg,
                                np.random.default_rng(v))
        assert np.array_equal(img, one)
    with pytest.raises(ValueError, match="one rng per view"):
        render_scene_views(scene, calib, cfg, [0, 1], [None])


def test_background_drawn_last_matches_the_z_buffer():
    """A quad behind every other one is drawn last where nothing else was hit: the same samples as the z-buffer.
    A plane crossing the background (a corner beyond it) must keep the background in the z-buffer."""
    import dataclasses

    from lfgraph.datasets.render import sample_rays
    from lfgraph.datasets.scene import _prepare, _sample

    calib = _rig(size=(96, 64), f=90.0)
    scene = make_scene(SceneConfig(objects=6, texels_per_m_at_1m=200), np.random.default_rng(4))
    rays = sample_rays(calib.intrinsics[1], calib.image_size_px, 2)
    prepared = _prepare(scene, calib.view_T_ref(1), None)
    assert prepared[0].behind_all and not any(q.behind_all for q in prepared[1:])
    _, last = _sample(prepared, rays, want_texture=True)
    _, z_buffered = _sample([dataclasses.replace(q, behind_all=False) for q in prepared], rays, want_texture=True)
    assert np.array_equal(last, z_buffered)
    bg = scene.quads[0]
    crossing = TexturedQuad(bg.centre - [0, 0, 0.5], np.array([0.5, 0, 0.0]), np.array([0, 0.5, 1.0]),
                            bg.texture[:8, :8])
    assert not any(q.behind_all for q in _prepare(Scene((bg, crossing)), np.eye(4), None))
