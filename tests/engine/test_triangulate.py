"""All views' projections at once (lfgraph.engine.triangulate.project_views) against each view's own camera model."""

import numpy as np
import pytest

from lfgraph.core.camera import project_world
from lfgraph.datasets.rig import RigConfig, make_rig
from lfgraph.engine.triangulate import project_views

SAME_PROJECTION_PX = 1e-9  # the batched lens table and one Intrinsics.project per view: the same model


@pytest.mark.parametrize("lens", [{}, {"lens": "fisheye", "k1": -0.02, "k2": 0.005},
                                  {"lens": "unified", "xi": 0.9, "k1": -0.1, "k2": 0.02}])
def test_project_views_is_each_views_projection_and_nan_behind(lens):
    rig = make_rig(RigConfig(rows=2, cols=3, **lens), np.random.default_rng(3))
    rng = np.random.default_rng(4)
    pts = rng.normal(size=(200, 3)) * [0.4, 0.4, 0.2] + [0.0, 0.0, 2.0]
    pts[0, 2] = -1.0  # behind every view
    px = project_views(rig, pts)
    assert px.shape == (rig.num_views, len(pts), 2)
    assert np.all(np.isnan(px[:, 0]))
    for v in range(rig.num_views):
        expected = project_world(rig.intrinsics[v], rig.view_T_ref(v), pts[1:])
        assert np.max(np.abs(px[v, 1:] - expected)) < SAME_PROJECTION_PX
