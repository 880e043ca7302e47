"""Rings through refine and check (issue 41): the tracker chosen by the geometry, the transfer at infinity in each
view's own image, and a rendered converging ring with its truth."""

import json

import numpy as np
import pytest

import lfgraph as lf
from lfgraph.core.geometry import make_T, rotation_from_rotvec
from lfgraph.core.grid import ViewGrid
from lfgraph.judge.evaluation import transfer_error_at_infinity
from lfgraph.refinement.trackers import AutoTracker
from tests.core.test_free_arrangement import ring_calibration

TURN_DEG = 0.1  # a pan of one view moves its own image by f (1 + x^2 / f^2) angle at x px from the centre
RING_KNOCK_DEG, RING_KNOCK_MM = 1.0, 3.0
NEVER_WORSE_PX = 1e-9  # a view kept is exactly its input; one written must be closer to the truth
ROUND_OFF_PX = 1e-9  # views not turned: the same projections to round-off
MIRROR_BIAS_PX = 0.02  # px: a keypoint and its mirror image's, mapped back, agree in the median to within this
# (OpenCV's default first octave puts both 0.25 px too far right and down: they disagree by 0.5 px)
MIRROR_MATCH_PX = 1.0  # px: a keypoint's twin in the mirror image lies within this
TEMPLE_POSITION_SIGMAS = 2.0  # a written position's error within this many of its reported (3-axis) sigma
TEMPLE_HELDOUT_GAIN = 10.0  # the whole refit predicts held-out tracks this many times better than the knocked input


def test_the_geometry_chooses_the_tracker():
    auto = AutoTracker()
    assert auto.choose(ViewGrid(3, 3)) == lf.ChainTracker()
    assert auto.choose(ring_calibration().grid) is auto.sift  # 30 deg between neighbours: descriptors
    line = ring_calibration(3).replace(ref_T_view=np.stack([make_T(np.eye(3), [0.1 * k, 0, 0]) for k in range(3)]))
    assert auto.choose(line.grid) == lf.ChainTracker()  # free but parallel: KLT sees the reference's features


def test_a_rings_transfer_at_infinity_is_each_views_own_image():
    truth = ring_calibration()
    poses = truth.ref_T_view.copy()
    v = 6  # opposite the reference: none of the reference's directions reaches its image
    poses[v] = poses[v] @ make_T(rotation_from_rotvec([0.0, np.radians(TURN_DEG), 0.0]), np.zeros(3))
    moved = transfer_error_at_infinity(truth.replace(ref_T_view=poses), truth)
    i, w = truth.intrinsics[v], truth.image_size_px[0]
    least = i.fx * np.radians(TURN_DEG)  # at the centre; at the image's side edge (1 + (w / 2 f)^2) times that
    assert least < moved[v] < least * (1 + (w / 2 / i.fx) ** 2)
    assert np.all(np.delete(moved, v) < ROUND_OFF_PX)


def test_sift_keypoints_carry_no_offset():
    """The truth is the mirror: a feature at column x of a W-wide image is at W - 1 - x in its left-right mirror
    (rows likewise), so any constant offset of the detector shows as twice itself between the two. A ring's views
    take a common offset as turns growing around the ring (the sweep's seed 78: 0.09 deg, 5 sigma)."""
    from lfgraph.datasets.ring import RingConfig, ring_capture
    from lfgraph.refinement.unordered import sift_features

    image = ring_capture(RingConfig(views=8), frames=1, seed=3).frames[0][0]
    h, w = image.shape
    pts, _ = sift_features(image)
    for axis, size in ((0, w), (1, h)):
        mirrored, _ = sift_features(np.flip(image, axis=1 - axis).copy())
        mirrored[:, axis] = size - 1 - mirrored[:, axis]
        d = np.linalg.norm(pts[:, None] - mirrored[None], axis=-1)
        twin = d.argmin(axis=1)
        near = d[np.arange(len(pts)), twin] < MIRROR_MATCH_PX
        assert near.sum() > len(pts) // 2
        assert abs(np.median(pts[near, axis] - mirrored[twin[near], axis])) < 2 * MIRROR_BIAS_PX


@pytest.mark.slow
def test_a_rendered_ring_through_the_commands(tmp_path, capsys):
    """check finds no drift on an unknocked ring; refine repairs a knocked one, never worse, through the CLI. The
    unknocked one is stored as a grid (a file from before free arrangements): check says it treats it as free, on
    standard error, so that its ``--json`` standard output parses."""
    from lfgraph.cli import main
    from lfgraph.datasets.ring import RingConfig, ring_capture
    from lfgraph.io.capture import write_frame

    for name, knock in (("still", (0.0, 0.0)), ("knocked", (RING_KNOCK_DEG, RING_KNOCK_MM))):
        cap = ring_capture(RingConfig(views=12), frames=2, knock_deg=knock[0], knock_mm=knock[1], seed=5)
        for f, images in enumerate(cap.frames):
            write_frame(tmp_path / name, f"{f:03d}", images, cap.truth.grid, layout="folders")
        stored = cap.original if name == "knocked" else cap.original.replace(
            grid=lf.ViewGrid(1, cap.original.num_views, cap.original.grid.reference))
        stored.save(tmp_path / f"{name}.json")
        cap.truth.save(tmp_path / f"{name}-truth.json")
    capsys.readouterr()
    assert main(["check", str(tmp_path / "still.json"), str(tmp_path / "still"), "--json"]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out)["verdict"] and "note:" in err and "note:" not in out
    assert main(["refine", str(tmp_path / "knocked.json"), str(tmp_path / "knocked"), "-o",
                 str(tmp_path / "refined.json"), "--quiet"]) == 0
    truth = lf.Calibration.load(tmp_path / "knocked-truth.json")
    refined = lf.Calibration.load(tmp_path / "refined.json")
    assert refined.grid.is_free
    before = transfer_error_at_infinity(lf.Calibration.load(tmp_path / "knocked.json"), truth)
    after = transfer_error_at_infinity(refined, truth)
    verdicts = refined.metrics["refinement"]["verdicts"]
    written = np.array([v["applied"] for v in verdicts])
    assert written.sum() >= 3, json.dumps([v["verdict"] for v in verdicts])
    assert np.all(after[written] < before[written]) and np.all(after <= before + NEVER_WORSE_PX)


@pytest.mark.slow
def test_the_middlebury_temple_ring_knocked_as_a_whole_is_written_whole(test_data):
    """templeSparseRing perturbed by 0.5 deg and 1 % of the neighbour baseline (2.24 mm), every view: one by one the
    views' changes do not stand out against their pan traded for sideways motion, and writing only some beside their
    knocked neighbours predicts the pairs between them no better (nothing was written); every view written together
    is what the held-out tracks confirm. Every rotation comes back closer to the published cameras; a position may
    not (the data leave 0.5-4 mm there, the knock is 2.24 mm), but within its reported sigma, and closer over the
    ring."""
    from lfgraph.datasets.middlebury import load_mview

    truth, images = load_mview(test_data / "middlebury_temple")
    rng = np.random.default_rng(0)
    poses = truth.ref_T_view.copy()
    for v in range(1, truth.num_views):
        axis, direction = rng.normal(size=3), rng.normal(size=3)
        poses[v] = poses[v] @ make_T(rotation_from_rotvec(axis / np.linalg.norm(axis) * np.radians(0.5)),
                                     direction / np.linalg.norm(direction) * 0.01 * 0.224)
    start = truth.replace(ref_T_view=poses)
    refined, report = lf.refine(start, [np.stack(images)])
    e0, e1 = lf.evaluate(start, truth), lf.evaluate(refined, truth)
    free = np.arange(truth.num_views) != truth.grid.reference
    assert all(v.applied for v in report.verdicts if v.view != truth.grid.reference)
    assert np.all(e1.rotation_deg[free] < e0.rotation_deg[free])
    p0, p1 = np.linalg.norm(e0.position_mm, axis=1), np.linalg.norm(e1.position_mm, axis=1)
    sigma = np.array([np.linalg.norm(v.sigma_position_mm) for v in report.verdicts])
    assert np.all(p1[free] < TEMPLE_POSITION_SIGMAS * sigma[free])
    assert np.sqrt(np.mean(p1[free] ** 2)) < np.sqrt(np.mean(p0[free] ** 2))
    assert report.heldout_after_px < report.heldout_before_px / TEMPLE_HELDOUT_GAIN


def test_a_free_arrangements_view_no_fold_refitted_is_not_confirmed():
    """A view every fold refit held (too few observations without its fold) was never tested by held-out tracks: in a
    free arrangement it is not written (dinoSparseRing perturbed, seed 3, under a looser held-out rule: a view of 64
    observations went 0.5 -> 2.1 deg with the held-out RMS the input's to 4 decimals). A grid keeps its rule."""
    from lfgraph.refinement.heldout import untested_views

    ring = ring_calibration()
    assert untested_views(ring, {1, 2}, [frozenset({1}), frozenset({1, 3})]) == {1}
    assert untested_views(ring, {1, 2}, []) == frozenset()  # no folds: nothing to ask
    grid = ring.replace(grid=ViewGrid(1, ring.num_views, 0))
    assert untested_views(grid, {1, 2}, [frozenset({1})]) == frozenset()


def test_tracks_seen_from_one_place_test_nothing_and_a_whole_ring_is_asked_only_when_every_view_was_tested():
    """A track of views at one place has no depth: the held-out test leaves it out (templeSparseRing's views 0 and
    10: one such track came back 670 px off through a ring 0.004-0.36 deg from the truth). The whole free
    arrangement is asked only when no view was held by the fit or a fold refit, some view changed significantly, and
    the rig is free."""
    from types import SimpleNamespace

    from lfgraph.refinement.heldout import one_place
    from lfgraph.refinement.whole import whole_views

    ring = ring_calibration()
    poses = ring.ref_T_view.copy()
    poses[5][:3, 3] = poses[0][:3, 3] + 1e-6  # view 5 stands where view 0 does
    ring = ring.replace(ref_T_view=poses)
    valid = np.zeros((ring.num_views, 3), dtype=bool)
    valid[[0, 5], 0] = True  # one place
    valid[[0, 1], 1] = True  # neighbours
    valid[[0, 5, 6], 2] = True  # one place and another
    assert one_place(ring, valid).tolist() == [True, False, False]

    fit = SimpleNamespace(held=frozenset())
    moved = {1: ("roll",), 2: ()}
    everyone = frozenset(range(1, ring.num_views))
    assert whole_views(ring, fit, [frozenset(), frozenset()], moved) == everyone
    assert whole_views(ring, fit, [frozenset({3}), frozenset()], moved) == frozenset()  # a fold held view 3
    assert whole_views(ring, SimpleNamespace(held=frozenset({4})), [frozenset()], moved) == frozenset()
    assert whole_views(ring, fit, [], moved) == frozenset()  # no folds: nothing to confirm it
    assert whole_views(ring, fit, [frozenset()], {1: (), 2: ()}) == frozenset()  # nothing significant
    grid = ring.replace(grid=ViewGrid(1, ring.num_views, 0))
    assert whole_views(grid, fit, [frozenset()], moved) == frozenset()
