"""A free arrangement (issue 41): views that are not a grid (a ring), their neighbours from their poses."""

import numpy as np
import pytest

from lfgraph.core.calibration import Calibration, CalibrationFileError
from lfgraph.core.camera import Intrinsics
from lfgraph.core.errors import RectificationError
from lfgraph.core.geometry import invert_T, make_T, rotation_from_rotvec
from lfgraph.core.grid import ViewGrid, free_grid
from lfgraph.core.grid_design import free_when_not_parallel

RING_VIEWS = 12
RING_STEP_DEG = 360.0 / RING_VIEWS
ANGLE_TOLERANCE_DEG = 1e-6


def ring_poses(n: int = RING_VIEWS, radius_m: float = 1.0) -> np.ndarray:
    """(n, 4, 4) ref_T_view of views evenly around the origin, each aimed at it (y down), in view 0's frame."""
    world = []
    for k in range(n):
        a = 2 * np.pi * k / n
        world.append(make_T(rotation_from_rotvec([0.0, -a, 0.0]), radius_m * np.array([np.sin(a), 0, -np.cos(a)])))
    return np.stack([invert_T(world[0]) @ t for t in world])


def ring_calibration(n: int = RING_VIEWS) -> Calibration:
    return Calibration(ViewGrid(1, n, 0, "free"), (320, 240), (Intrinsics(300, 300, 159.5, 119.5),) * n, ring_poses(n))


def test_a_ring_links_each_view_to_its_two_neighbours_at_the_ring_step():
    grid = ring_calibration().grid
    assert grid.is_free and str(grid) == f"1x{RING_VIEWS} free"
    assert set(grid.links) == {(k, k + 1) for k in range(RING_VIEWS - 1)} | {(0, RING_VIEWS - 1)}
    assert np.allclose(grid.link_deg, RING_STEP_DEG, atol=ANGLE_TOLERANCE_DEG)
    assert grid.neighbours(0) == [1, RING_VIEWS - 1]


def test_the_chain_of_a_free_arrangement_is_a_tree_from_the_reference():
    for ref in (0, 5):
        grid = ring_calibration().with_reference(ref).grid
        reached = {ref}
        for a, b in grid.chain():
            assert a in reached and b not in reached and (min(a, b), max(a, b)) in grid.links
            reached.add(b)
        assert reached == set(range(RING_VIEWS))


def test_loose_views_are_always_connected():
    rng = np.random.default_rng(0)
    poses = np.stack([np.eye(4)] + [make_T(rotation_from_rotvec(rng.normal(0, 0.5, 3)), rng.normal(0, 2, 3))
                                    for _ in range(9)])
    grid = free_grid(poses, links=1)
    reached = {0} | {b for _, b in grid.chain()}
    assert reached == set(range(10))


def test_rows_and_columns_are_a_grids_alone():
    grid = ring_calibration().grid
    with pytest.raises(ValueError, match="free arrangement"):
        grid.horizontal_pairs()
    with pytest.raises(ValueError, match="arrangement must be one of grid, free"):
        ViewGrid(1, 3, 0, "ring")
    with pytest.raises(ValueError, match="links belong to a free arrangement"):
        ViewGrid(1, 3, 0, "grid", ((0, 1),))


def test_calibration_json_keeps_the_arrangement_and_derives_the_links(tmp_path):
    calib = ring_calibration()
    calib.save(tmp_path / "ring.json")
    back = Calibration.load(tmp_path / "ring.json")
    assert back.grid == calib.grid and back.grid.links == calib.grid.links
    data = calib.to_dict()
    assert data["grid"] == {"rows": 1, "cols": RING_VIEWS, "reference": 0, "arrangement": "free"}
    data["grid"]["arrangement"] = "dome"
    with pytest.raises(CalibrationFileError, match="grid.*arrangement must be one of grid, free"):
        Calibration.from_dict(data, "ring.json")
    assert "arrangement" not in ring_calibration().replace(grid=ViewGrid(1, RING_VIEWS)).to_dict()["grid"]


def test_a_ring_stored_as_a_row_is_taken_as_free_with_a_note():
    row = ring_calibration().replace(grid=ViewGrid(1, RING_VIEWS))
    free, note = free_when_not_parallel(row)
    assert free.grid.is_free and "not near-parallel" in note
    assert free_when_not_parallel(free) == (free, None)


def test_rectification_refuses_a_free_arrangement_by_name():
    from lfgraph.rectification.checks import check_rectifiable

    with pytest.raises(RectificationError, match="free arrangement"):
        check_rectifiable(ring_calibration())
