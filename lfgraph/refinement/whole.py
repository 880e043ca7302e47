"""A free arrangement written whole: when its views, tested one by one, leave a candidate the held-out tracks refuse,
every view of the MAP fit is written together if the held-out tracks confirm that.

A ring's or a loose rig's views are known only relative to their neighbours (tracks between views tens of degrees
apart, which trade a view's pan against its sideways motion). Knocked as a whole, each view's change can be large at
infinity and still not stand out against what the data leave undetermined there, so `assess` keeps it; writing the
views that do stand out beside their neighbours' knocked poses then predicts the pairs between them no better than
the input. templeSparseRing perturbed 0.5 deg / 2.24 mm (seed 0): the written views' candidate predicted held-out
tracks at 4.31 px against 6.76 px with the input and 0.10 px on its own tracks (refused: the frames disagree), while
the fold refits of every view predicted them at 0.12 px; that fit has every rotation closer to the truth and 14 of
15 positions (the 15th 2.24 -> 2.43 mm, within its 2 mm sigma).

The whole fit is written only when:
- the arrangement is free (a grid's views are judged one by one, as its benchmarks were set);
- no view was held by the fit or by any fold refit (too few observations): a view held at its knocked pose pulls the
  neighbours written beside it (the rendered ring sweep, seed 97, under an earlier looser rule: 17.6 -> 26.3 px);
- some view changed significantly, the tracks are not mismatched, and no other camera's intrinsics explain them;
- every fold's refit of all views predicts its left-out tracks at least `WHOLE_MIN_IMPROVEMENT` times better than the
  input (the knock outweighs what the fit itself gets wrong), and consistently with its own fit
  (`lfgraph.refinement.heldout.heldout_test`'s rule).
"""

from __future__ import annotations

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.refinement.config import RefineConfig
from lfgraph.refinement.heldout import heldout_test
from lfgraph.refinement.verdicts import intrinsics_mismatch

WHOLE_MIN_IMPROVEMENT = 5.0  # the input predicts the held-out tracks at least this x worse than the whole refit: the
# knock must outweigh what the fit itself gets wrong. Rendered ring sweep (seeds 0-99): rings knocked 1.3-1.8 deg,
# 6.5-13x, were written 2.1-2.8x closer at infinity (error / sigma <= 1.9; the temple 58x); rings knocked 0.27-0.30
# deg, 2.6-3.2x, came back 1.2x farther: there what the SIFT tracks' own offsets leave in the fit (2 px where the
# sigma says 0.7) is the size of the knock


def whole_views(calib: Calibration, fit, fold_held: list[frozenset[int]],
                significant: dict[int, tuple[str, ...]]) -> frozenset[int]:
    """The views to write together (every view but the reference) when the arrangement qualifies (module
    docstring), else none."""
    ref = calib.grid.reference
    held = set(fit.held).union(*fold_held) - {ref}
    if not calib.grid.is_free or not fold_held or held or not any(significant.values()):
        return frozenset()
    return frozenset(v for v in range(calib.num_views) if v != ref)


def confirmed(accepted: bool, before_px: float, after_px: float) -> bool:
    """Whether the held-out test accepted the whole candidate and it predicts the held-out tracks at least
    `WHOLE_MIN_IMPROVEMENT` times better than the input."""
    return bool(accepted and before_px >= WHOLE_MIN_IMPROVEMENT * after_px)


def written_whole(calib: Calibration, fit, px: np.ndarray, ok: np.ndarray, folds: tuple[list, list, list],
                  significant: dict[int, tuple[str, ...]], foreign_checked: bool, config: RefineConfig,
                  observer) -> tuple[tuple[frozenset[int], tuple] | None, tuple[float, float] | None]:
    """When the views one by one were not confirmed: (the views written whole and `heldout_test`'s result for them,
    or None; another camera's evidence, `intrinsics_mismatch`, when it ran here and found it). ``folds``: the fold
    refits, their left-out tracks and the views each held; ``foreign_checked``: whether that test already ran (and
    found nothing) for the views one by one."""
    fold_calibs, fold_tests, fold_held = folds
    views = whole_views(calib, fit, fold_held, significant)
    if not views:
        return None, None
    foreign = None if foreign_checked else intrinsics_mismatch(calib, px, ok, fit, config, observer)
    if foreign is not None:
        return None, foreign
    observer.log(f"the views one by one were not confirmed; the {len(views)} views of the free arrangement written "
                 f"together:")
    test = heldout_test(calib, fit, px, ok, set(views), fold_calibs, fold_tests, config, observer)
    return ((views, test) if confirmed(test[1], test[3], test[4]) else None), None
