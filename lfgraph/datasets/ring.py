"""A rendered converging ring with its truth: views on a circle around textured boxes, each aimed at the centre,
inside a textured room (so every view sees texture behind the objects) — the volumetric-capture rig that is no grid
(a free arrangement, `lfgraph.core.grid.free_grid`).

    cap = ring_capture(RingConfig(views=12), frames=2, knock_deg=0.5, knock_mm=5, seed=3)
    refined, report = lf.refine(cap.original, cap.frames)

World frame of the construction: y down (as a camera's), the ring in the x-z plane around the origin; everything is
then expressed in the reference view's frame. Seeded and pure: the rig from (seed,), its knock from (seed, 1), frame
f's scene from (seed, f) and view v's sensor noise from (seed, f, v).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.camera import Intrinsics
from lfgraph.core.geometry import invert_T, make_T, rotation_from_rotvec
from lfgraph.core.grid import ViewGrid
from lfgraph.datasets.rig import ShakeConfig, shake_rig
from lfgraph.datasets.scene import Scene, SceneConfig, TexturedQuad, dead_leaves_texture, render_scene_views


@dataclass(frozen=True)
class RingConfig:
    """A converging ring of views and the room it stands in.

    Attributes:
        views: number of views, evenly spaced over 360 degrees (8-16: 45-22.5 degrees apart).
        radius_m: distance of every view from the centre it is aimed at.
        elevation_deg: how far the views look down at the centre.
        image_size_px: (width, height) of every view.
        focal_px: focal length (fx = fy) of every view, before ``focal_jitter_px``.
        focal_jitter_px, principal_jitter_px: std of the per-view jitter of fx, fy and cx, cy.
        aim_jitter_deg, place_jitter_mm: std per axis of each view's rotation and position off its ideal place.
        objects: textured boxes near the centre (within ``object_spread_m``).
        room_half_m: half the side of the square room (walls, floor and ceiling textured).
    """

    views: int = 12
    radius_m: float = 1.0
    elevation_deg: float = 15.0
    image_size_px: tuple[int, int] = (480, 360)
    focal_px: float = 480.0
    focal_jitter_px: float = 3.0
    principal_jitter_px: float = 3.0
    aim_jitter_deg: float = 1.0
    place_jitter_mm: float = 5.0
    objects: int = 4
    object_spread_m: float = 0.3
    room_half_m: float = 3.0

    def __post_init__(self) -> None:
        if not 3 <= self.views <= 360:
            raise ValueError(f"a ring needs 3 to 360 views, got {self.views}")
        if not 0 < self.radius_m < self.room_half_m:
            raise ValueError(f"need 0 < radius_m < room_half_m, got {self.radius_m} and {self.room_half_m}")
        if not self.object_spread_m + 0.2 < self.radius_m:
            raise ValueError(f"the objects (spread {self.object_spread_m} m) must leave room for the views at "
                             f"{self.radius_m} m")


@dataclass(frozen=True)
class RingCapture:
    """A rendered ring: ``original`` (the calibration before the knock), ``truth`` (the rig the frames were rendered
    with), ``frames`` (one (V, H, W) uint8 array per frame), the config and the seed."""

    original: Calibration
    truth: Calibration
    frames: list[np.ndarray]
    config: RingConfig
    seed: int


def _aimed(position: np.ndarray) -> np.ndarray:
    """(4, 4) world_T_view of a view at ``position`` looking at the origin, its y axis towards world +y (down)."""
    z = -position / np.linalg.norm(position)
    y = np.array([0.0, 1.0, 0.0]) - z[1] * z
    y /= np.linalg.norm(y)
    return make_T(np.column_stack([np.cross(y, z), y, z]), position)


def make_ring_rig(config: RingConfig, rng: np.random.Generator) -> tuple[Calibration, np.ndarray]:
    """(the ring as a free-arrangement calibration, (4, 4) world_T_ref): views evenly around the centre, aimed at it,
    each jittered by ``aim_jitter_deg`` / ``place_jitter_mm`` per axis, intrinsics by their jitters."""
    e = np.radians(config.elevation_deg)
    world_T_view = []  # noqa: N806
    for k in range(config.views):
        a = 2 * np.pi * k / config.views
        place = config.radius_m * np.array([np.sin(a) * np.cos(e), -np.sin(e), -np.cos(a) * np.cos(e)])
        T = _aimed(place)  # noqa: N806
        turn = rotation_from_rotvec(np.radians(config.aim_jitter_deg) * rng.standard_normal(3))
        T = make_T(T[:3, :3] @ turn, T[:3, 3] + 1e-3 * config.place_jitter_mm * rng.standard_normal(3))  # noqa: N806
        world_T_view.append(T)
    world_T_ref = world_T_view[0]  # noqa: N806
    ref_T_view = np.stack([invert_T(world_T_ref) @ T for T in world_T_view])  # noqa: N806
    ref_T_view[0] = np.eye(4)
    w, h = config.image_size_px
    intrinsics = []
    for _ in range(config.views):
        f = config.focal_px + config.focal_jitter_px * rng.standard_normal(2)
        c = np.array([(w - 1) / 2, (h - 1) / 2]) + config.principal_jitter_px * rng.standard_normal(2)
        intrinsics.append(Intrinsics(float(f[0]), float(f[1]), float(c[0]), float(c[1])))
    grid = ViewGrid(1, config.views, 0, "free")
    return Calibration(grid, (w, h), tuple(intrinsics), ref_T_view), world_T_ref


def _box(centre: np.ndarray, half: np.ndarray, turn: np.ndarray, texels_per_m: float,
         rng: np.random.Generator) -> list[TexturedQuad]:
    """The six textured faces of a box (world frame): ``half`` (3,) half sides, turned by ``turn`` (3, 3)."""
    faces = []
    for axis in range(3):
        u, v = [k for k in range(3) if k != axis]
        for sign in (-1.0, 1.0):
            c = centre + sign * half[axis] * turn[:, axis]
            size = (max(16, int(2 * half[u] * texels_per_m)), max(16, int(2 * half[v] * texels_per_m)))
            faces.append(TexturedQuad(c, half[u] * turn[:, u], half[v] * turn[:, v],
                                      dead_leaves_texture((min(size[0], 2048), min(size[1], 2048)), rng)))
    return faces


def make_ring_scene(config: RingConfig, world_T_ref: np.ndarray, rng: np.random.Generator,  # noqa: N803
                    texels_per_m: float = 700.0) -> Scene:
    """Textured boxes near the centre inside a textured room, in the reference view's frame. Seeded and pure."""
    quads = _box(np.zeros(3), np.full(3, config.room_half_m), np.eye(3), texels_per_m / 4, rng)  # the room
    for _ in range(config.objects):
        centre = rng.uniform(-config.object_spread_m, config.object_spread_m, 3) * [1.0, 0.5, 1.0]
        half = rng.uniform(0.06, 0.16, 3)
        quads += _box(centre, half, rotation_from_rotvec(rng.uniform(-np.pi, np.pi, 3)), texels_per_m, rng)
    ref_T_world = invert_T(world_T_ref)  # noqa: N806
    R, t = ref_T_world[:3, :3], ref_T_world[:3, 3]  # noqa: N806
    return Scene(tuple(TexturedQuad(R @ q.centre + t, R @ q.axis_u, R @ q.axis_v, q.texture) for q in quads))


RING_RENDER = SceneConfig(depth_m=(0.5, 1.5), background_depth_m=4.0)  # the renderer's settings: 2x2 samples,
# blur 0.5 px, noise 1 grey level (the depths are not used: the ring draws its own scene)


def ring_capture(config: RingConfig = RingConfig(), frames: int = 1, knock_deg: float = 0.0, knock_mm: float = 0.0,
                 seed: int = 0) -> RingCapture:
    """A ring rendered with its truth: the rig from ``seed``, knocked (each non-reference view turned by up to
    ``knock_deg`` about a random axis and moved by up to ``knock_mm`` per axis; drawn from (seed, 1)), and
    ``frames`` frames rendered with the knocked rig."""
    original, world_T_ref = make_ring_rig(config, np.random.default_rng(seed))  # noqa: N806
    truth = original
    if knock_deg > 0 or knock_mm > 0:
        truth = shake_rig(original, ShakeConfig(rot_deg=knock_deg, trans_mm=knock_mm, axis="any"),
                          np.random.default_rng([seed, 1]))
    images = []
    for f in range(frames):
        scene = make_ring_scene(config, world_T_ref, np.random.default_rng([seed, f]))
        rngs = [np.random.default_rng([seed, f, v]) for v in range(truth.num_views)]
        images.append(render_scene_views(scene, truth, RING_RENDER, rngs=rngs))
    return RingCapture(original, truth, images, config, seed)
