"""Named synthetic scenes: the paper's cameras and small rigs for tests."""

from __future__ import annotations

from dataclasses import dataclass, field

from lfgraph.datasets.checkerboard import CheckerboardConfig
from lfgraph.datasets.rig import RigConfig
from lfgraph.detect.board import BoardSpec


@dataclass(frozen=True)
class NamedScene:
    """A rig plus how it is shown a board (``checkerboard``) and/or a textured scene (``frames`` of it)."""

    name: str
    description: str
    rig: RigConfig
    checkerboard: CheckerboardConfig = field(default_factory=CheckerboardConfig)
    frames: int = 10
    scene_depth_m: tuple[float, float] = (2.0, 6.0)


SCENES: dict[str, NamedScene] = {
    "paper-4x4": NamedScene(
        "paper-4x4",
        "the paper's camera: 4x4 views, 960x960 px, f = 850 px, 6 mm pitch, 11x8-corner board with 20 mm squares, "
        "40 frames",
        RigConfig(rows=4, cols=4, pitch_m=0.006, image_size_px=(960, 960), focal_px=850.0),
        CheckerboardConfig(board=BoardSpec(11, 8, 0.020), frames=40, distance_m=(0.35, 0.9)),
        frames=10, scene_depth_m=(0.5, 2.0)),
    "paper-5x5": NamedScene(
        "paper-5x5",
        "the paper's synthetic refinement set: 5x5 views, 512x512 px, f = 700 px, 100 mm pitch, scene at 2-6 m, "
        "10 frames",
        RigConfig(rows=5, cols=5, pitch_m=0.100, image_size_px=(512, 512), focal_px=700.0, k1=-0.05, k2=0.01,
                  principal_jitter_px=4.0, trans_jitter_mm=0.5),
        CheckerboardConfig(board=BoardSpec(9, 6, 0.100), frames=30, distance_m=(1.5, 3.5)),
        frames=10, scene_depth_m=(2.0, 6.0)),
    "small-2x2": NamedScene(
        "small-2x2",
        "a small 2x2 rig, 320x240 px, f = 300 px, 10 mm pitch, 7x5-corner board with 15 mm squares, 8 frames",
        RigConfig(rows=2, cols=2, pitch_m=0.010, image_size_px=(320, 240), focal_px=300.0, focal_jitter_px=2.0,
                  principal_jitter_px=3.0),
        CheckerboardConfig(board=BoardSpec(7, 5, 0.015), frames=8, distance_m=(0.25, 0.45)),
        frames=3, scene_depth_m=(1.0, 3.0)),
    "fisheye-1x3": NamedScene(
        "fisheye-1x3",
        "a line of 3 wide-angle (fisheye, Kannala-Brandt) views, 640x480 px, f = 260 px (~120 deg across the "
        "diagonal), 40 mm pitch, 9x6-corner board with 30 mm squares, 24 frames",
        RigConfig(rows=1, cols=3, reference=1, pitch_m=0.040, image_size_px=(640, 480), focal_px=260.0,
                  k1=0.02, k2=-0.005, focal_jitter_px=2.0, principal_jitter_px=3.0, distortion_jitter=0.004,
                  lens="fisheye"),
        CheckerboardConfig(board=BoardSpec(9, 6, 0.030), frames=24, distance_m=(0.15, 0.35)),
        frames=3, scene_depth_m=(1.0, 3.0)),
}


def get_scene(name: str) -> NamedScene:
    """A named scene; raises ValueError listing the known names."""
    try:
        return SCENES[name]
    except KeyError:
        raise ValueError(f"unknown scene {name!r}; known scenes: {', '.join(sorted(SCENES))}") from None
