"""Synthetic light fields in memory, exactly as ``lfgraph synth scene`` writes them: a named scene's rig, the same
rig knocked, and its rendered frames — for scripts and studies that want (original, truth, frames) without files.

    cap = lf.synth.scene_capture("small-2x2", frames=2, shake_rot_deg=0.5, seed=3)
    refined, report = lf.refine(cap.original, cap.frames)
    print(lf.evaluate(refined, cap.truth).summary()["rms_transfer_px"])

Wrong matches are the tracker's, not the images': ``scene_capture(..., outliers="0.05:2-8")`` gives the capture a
``tracker`` (an `OutlierTracker` around the chain tracker) that moves 5 % of the non-reference observations by 2-8 px;
refine with ``lf.RefineConfig(tracker=cap.tracker, ...)`` (``lfgraph refine --outliers 0.05:2-8`` on a written set).

Frame f's scene is drawn from the generator seeded (seed, f) and view v's sensor noise from (seed, f, v), the rig
from seed and its knock from (seed, 1): the same numbers as the command line's, so a script and a capture written by
``lfgraph synth scene --seed S`` hold the same images (tested).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.datasets.rig import RigConfig, ShakeConfig, make_rig, shake_rig
from lfgraph.datasets.scene import SceneConfig, make_scene, render_scene_views
from lfgraph.datasets.scenes import SCENES, NamedScene, get_scene
from lfgraph.refinement.tracks import OutlierTracker

__all__ = ["SCENES", "OutlierTracker", "RigConfig", "SceneCapture", "ShakeConfig", "knocked_rig", "render_frame",
           "scene_capture", "scene_config"]


@dataclass(frozen=True)
class SceneCapture:
    """A rendered synthetic capture.

    Attributes:
        original: the array as calibrated (before the knock): what a refinement starts from.
        truth: the array the frames were rendered with (the knocked one; ``original`` when not knocked).
        frames: one (V, H, W) uint8 grayscale array per frame, views in the grid's row-major order.
        scene: the scene settings the frames were rendered with.
        seed: the seed of everything random.
        tracker: None (the default tracker), or the `OutlierTracker` of ``scene_capture(outliers=...)``: give it as
            ``RefineConfig(tracker=...)``.
    """

    original: Calibration
    truth: Calibration
    frames: list[np.ndarray]
    scene: SceneConfig
    seed: int
    tracker: OutlierTracker | None = None

    @property
    def knocked(self) -> bool:
        """Whether the frames were rendered with a knocked rig (``truth`` differs from ``original``)."""
        return self.original is not self.truth


def _named(name: str | NamedScene) -> NamedScene:
    if isinstance(name, NamedScene):
        return name
    if not isinstance(name, str):
        raise TypeError(f"scene must be a scene name ({', '.join(sorted(SCENES))}) or a NamedScene, got "
                        f"{type(name).__name__}")
    return get_scene(name)


def scene_config(name: str | NamedScene, keyboard: bool = False) -> SceneConfig:
    """The textured scene a named scene is shown (as ``lfgraph synth scene``): objects over its depth range, a
    background 1.4x beyond; ``keyboard`` for repetitive key caps instead of natural (dead-leaves) texture."""
    near, far = _named(name).scene_depth_m
    return SceneConfig(depth_m=(near, far), background_depth_m=far * 1.4,
                       kind="keyboard" if keyboard else "dead-leaves")


def knocked_rig(name: str | NamedScene, shake_rot_deg: float = 0.0, shake_trans_mm: float = 0.0,
                shake_axis: str = "any", seed: int = 0, **rig_changes) -> tuple[Calibration, Calibration]:
    """(original, truth): the named scene's rig drawn from ``seed`` and the same rig knocked — each non-reference
    view turned by up to ``shake_rot_deg`` (about a random axis with ``shake_axis="any"``, about its optical axis
    with ``"optical"``) and moved by up to ``shake_trans_mm`` per axis; truth is original when neither is set.
    ``rig_changes`` override fields of the scene's `RigConfig` (``rows``, ``cols``, ``image_size_px``, ...)."""
    rig = _named(name).rig
    if rig_changes:
        rig = dataclasses.replace(rig, **rig_changes)
    original = make_rig(rig, np.random.default_rng(seed))
    if not (shake_rot_deg > 0 or shake_trans_mm > 0):
        return original, original
    shake = ShakeConfig(rot_deg=shake_rot_deg, trans_mm=shake_trans_mm, axis=shake_axis)
    return original, shake_rig(original, shake, np.random.default_rng([seed, 1]))


def render_frame(truth: Calibration, scene: SceneConfig, seed: int, frame: int) -> np.ndarray:
    """Frame ``frame`` of a capture: (V, H, W) uint8, its scene from (seed, frame), view v's noise from
    (seed, frame, v)."""
    drawn = make_scene(scene, np.random.default_rng([seed, frame]))
    rngs = [np.random.default_rng([seed, frame, v]) for v in range(truth.num_views)]
    return render_scene_views(drawn, truth, scene, rngs=rngs)


def scene_capture(name: str | NamedScene = "paper-5x5", frames: int | None = None, *, shake_rot_deg: float = 0.0,
                  shake_trans_mm: float = 0.0, shake_axis: str = "any", keyboard: bool = False, seed: int = 0,
                  outliers: str | OutlierTracker | None = None, **rig_changes) -> SceneCapture:
    """Render a named scene's capture in memory: what ``lfgraph synth scene NAME --frames N --shake-rot-deg R
    --shake-trans-mm T --shake-axis A [--keyboard] --seed S`` writes, as arrays.

    Args:
        name: a scene of `SCENES` (``paper-4x4``, ``paper-5x5``, ``small-2x2``, ``fisheye-1x3``) or a `NamedScene`.
        frames: how many (default: the scene's own number).
        shake_rot_deg, shake_trans_mm, shake_axis: the knock (`knocked_rig`); none by default.
        keyboard: repetitive texture instead of natural texture.
        seed: the seed of the rig, the knock, the scenes and the noise (and of the wrong matches).
        outliers: wrong matches, ``"SHARE:MIN-MAX"`` (``"0.05:2-8"``: 5 % of the non-reference observations moved
            by 2-8 px) or an `OutlierTracker`: the capture's ``tracker``; None: none.
        rig_changes: `RigConfig` fields to override (``lf.synth.RigConfig``: rows, cols, pitch_m, image_size_px,
            focal_px, lens, ...).
    """
    named = _named(name)
    n = named.frames if frames is None else frames
    if not (isinstance(n, int | np.integer) and n >= 1):
        raise ValueError(f"frames must be a whole number >= 1, got {n!r}")
    original, truth = knocked_rig(named, shake_rot_deg, shake_trans_mm, shake_axis, seed, **rig_changes)
    scene = scene_config(named, keyboard)
    if outliers is not None and not isinstance(outliers, OutlierTracker):
        outliers = OutlierTracker.parse(outliers, seed=seed)
    return SceneCapture(original, truth, [render_frame(truth, scene, seed, f) for f in range(int(n))], scene, seed,
                        outliers)
