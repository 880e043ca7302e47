"""Self-calibration's staged steps: a stage thrown behind the views."""

from __future__ import annotations

import dataclasses

import numpy as np

import lfgraph.selfcal.stages as stages
from lfgraph.core.camera import project_world
from lfgraph.core.observer import BaseObserver
from lfgraph.engine.schedule import TrackState
from lfgraph.selfcal import Design, PooledTracks, SelfCalConfig

DESIGN = Design(4, 4, pitch_mm=6.0, focal_px=425.0, image_size_px=(480, 480))
DEPTH_M = (0.5, 2.0)


def test_a_stage_thrown_behind_the_views_is_run_again_damped(monkeypatch):
    """GTSAM's projection factors have zero error behind a camera: a plain run that ends there (here: made to, by
    mirroring its landmarks through the reference centre) is run again with damped steps, whose result is kept."""
    nominal = DESIGN.calibration()
    rng = np.random.default_rng(0)
    n = 400
    uv = rng.uniform(10.0, 470.0, (n, 2))
    z = np.exp(rng.uniform(*np.log(DEPTH_M), n))
    points = np.column_stack([nominal.intrinsics[0].undistort(uv) * z[:, None], z])
    pixels = np.stack([project_world(nominal.intrinsics[v], nominal.view_T_ref(v), points) for v in range(16)])
    valid = np.ones(pixels.shape[:2], dtype=bool)
    tracks = PooledTracks(pixels, valid, np.arange(n) % 5, 5, 5)
    real, damped_runs = stages.run_map_stage, []

    def mirrored_unless_damped(*args, damped=False, **kwargs):
        calib, pts, graph, values, iters = real(*args, damped=damped, **kwargs)
        damped_runs.append(damped)
        return calib, pts if damped else -pts, graph, values, iters

    monkeypatch.setattr(stages, "run_map_stage", mirrored_unless_damped)
    lines = []

    class Lines(BaseObserver):
        def log(self, message: str) -> None:
            lines.append(message)

    config = SelfCalConfig()
    config = dataclasses.replace(config, stages=config.stages[:1])
    state = TrackState.start(nominal, pixels, valid, points, tracks)
    out, _ = stages.run_stages(state, nominal, config.sigmas(DESIGN), DESIGN, config, Lines())
    assert damped_runs == [False, True]
    assert out.tracks.num_tracks == n
    assert any("again with damped steps" in line for line in lines)
