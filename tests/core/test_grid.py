import pytest

from lfgraph.core.grid import ViewGrid, parse_grid


def test_row_major_indices_and_names():
    g = ViewGrid(3, 4, 0)
    assert g.num_views == 12
    assert g.position(7) == (1, 3) and g.index(1, 3) == 7
    assert g.name(7) == "r01_c03"
    assert sorted(g.neighbours(5)) == [1, 4, 6, 9]
    assert sorted(g.neighbours(0)) == [1, 4]
    assert len(g.horizontal_pairs()) == 9 and len(g.vertical_pairs()) == 8


def test_paper_chain_from_corner_is_a_snake():
    # Paper Fig. 5: along the row, then into the next row at its end, back along it.
    assert ViewGrid(2, 3, 0).chain_order() == [0, 1, 2, 5, 4, 3]
    assert ViewGrid(2, 3, 5).chain_order() == [5, 4, 3, 0, 1, 2]
    for edge in ViewGrid(4, 4, 0).chain():
        assert edge[1] in ViewGrid(4, 4, 0).neighbours(edge[0])


@pytest.mark.parametrize(("rows", "cols", "ref"), [(4, 4, 0), (4, 4, 15), (3, 3, 4), (5, 5, 12), (1, 2, 1), (3, 5, 7)])
def test_chain_reaches_every_view_once_from_adjacent_views(rows, cols, ref):
    g = ViewGrid(rows, cols, ref)
    reached = {ref}
    for a, b in g.chain():
        assert a in reached, "a view is tracked from one not reached yet"
        assert b not in reached
        assert b in g.neighbours(a)
        reached.add(b)
    assert reached == set(range(g.num_views))


def test_parse_grid():
    assert parse_grid("4x4") == (4, 4)
    assert parse_grid(" 1X2 ") == (1, 2)
    assert parse_grid("1x1") == (1, 1)  # one camera: calibrated, not rectified
    for bad in ("4", "4x", "axb", "0x3", "2x0"):
        with pytest.raises(ValueError, match="grid"):
            parse_grid(bad)


def test_bad_grid_values():
    with pytest.raises(ValueError, match="reference view 16"):
        ViewGrid(4, 4, 16)
    with pytest.raises(ValueError, match="outside"):
        ViewGrid(2, 2).position(4)
    with pytest.raises(ValueError, match="outside"):
        ViewGrid(2, 2).index(2, 0)
