"""Graph fragments of the auto-refinement: scene landmarks seen by the views, the priors that hold what a stage
does not free, and the gauges. Each function returns a `gtsam.NonlinearFactorGraph` fragment merged with
``push_back``; noise models come from `lfgraph.factors.noise`.

Gauges: (1) the array's frame — the reference view's pose is held; scale, unobservable from a scene alone, is fixed
by one range (reference to the farthest view); (2) the hidden principal-point gauge — shifting each view's
principal point in proportion to its baseline while shifting every landmark's inverse depth leaves all images
unchanged; in the free fit (no priors) cx of the reference row's neighbour (cy of its column neighbour in a
single-column grid) is held whenever principal points are free, under MAP priors the drift priors fix it (holding
that cx exactly, together with the same view's pan, turned its real pan into a principal-point ramp over the grid:
`--stages paper` wrote cx 20-30 px off after 1-degree knocks, issue 24); (3) with nearly parallel views a common
zoom and shift of every view's fx, fy, cx, cy is unobservable too, so the reference view's intrinsics are held as
its pose is; (4) the same hidden mode in rotations: turning each view by delta * (-c_y, c_x, 0) (body x, y; c its
position) while shifting every landmark's inverse depth by delta leaves all images unchanged to first order. With
the intrinsics held this is *not* a gauge in a grid of three or more views: a pan moves every image point by
(1 + x^2) delta, a principal-point shift by delta, real knocks do not follow the ramp, and holding one view's pan
turned its real pan into a pan/tilt ramp across the grid (issue 24). In a stereo pair the mode *is* the second
view's pan (the data see it only through x*y vertical disparity): there it is held at its input under MAP priors
(`holds_rotation_gauge`). Everything else a stage does not pin is weakly determined, not a gauge: the MAP drift
priors hold it.
"""

from __future__ import annotations

from collections.abc import Sequence

import gtsam
import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.geometry import to_pose3
from lfgraph.factors.groups import CAL3DS2_INDICES, Group
from lfgraph.factors.keys import calib_key, landmark_key, view_pose_key
from lfgraph.factors.noise import HELD_SIGMA, MIN_SIGMA, range_noise
from lfgraph.factors.prior_table import POSE_TANGENT, calibration_vectors
from lfgraph.lenses import DEFAULT_LENS, lens_model

RANGE_GAUGE_SIGMA_M = 1e-3  # a pure gauge: any sigma keeps the range; 1e-6 m made LM fail on a 14 mm baseline
FOCAL_FREE_SIGMA_PX = 1e4  # fx, fy, cx, cy when a refinement stage frees them (no practical pull)


def _observations(valid: np.ndarray, pixels: np.ndarray) -> tuple[list[int], list[int], np.ndarray]:
    vs, js = np.nonzero(valid)
    return vs.tolist(), js.tolist(), pixels[vs, js]


def _by_lens(name: str, lens: str):
    """GTSAM's ``name`` class for a lens model (``TriangulationFactor`` + ``Cal3Fisheye``, ...)."""
    return lens_model(lens).gtsam(name)


def triangulation_factors(calib: Calibration, pixels: np.ndarray, valid: np.ndarray,
                          noise: gtsam.noiseModel.Base) -> gtsam.NonlinearFactorGraph:
    """Landmarks seen by constant cameras (`TriangulationFactorCal3DS2`, or its Cal3Fisheye / Cal3Unified twin by
    each view's lens): (V, N, 2) pixels, (V, N) valid."""
    graph = gtsam.NonlinearFactorGraph()
    lens = [i.lens for i in calib.intrinsics]
    cams = [_by_lens("PinholeCamera", lens[v])(to_pose3(calib.ref_T_view[v]), calib.intrinsics[v].to_gtsam())
            for v in range(calib.num_views)]
    vs, js, meas = _observations(valid, pixels)
    for v, j, uv in zip(vs, js, meas, strict=True):
        graph.add(_by_lens("TriangulationFactor", lens[v])(cams[v], uv, noise, landmark_key(j)))
    return graph


def projection_factors(calib: Calibration, pixels: np.ndarray, valid: np.ndarray,
                       noise: gtsam.noiseModel.Base) -> gtsam.NonlinearFactorGraph:
    """Landmarks seen by free poses with constant intrinsics (`GenericProjectionFactorCal3DS2`, or its Cal3Fisheye /
    Cal3Unified twin by each view's lens)."""
    graph = gtsam.NonlinearFactorGraph()
    cals = [calib.intrinsics[v].to_gtsam() for v in range(calib.num_views)]
    factor = [_by_lens("GenericProjectionFactor", i.lens) for i in calib.intrinsics]
    vs, js, meas = _observations(valid, pixels)
    for v, j, uv in zip(vs, js, meas, strict=True):
        graph.add(factor[v](uv, noise, view_pose_key(v), landmark_key(j), cals[v]))
    return graph


def sfm_factors(pixels: np.ndarray, valid: np.ndarray, noise: gtsam.noiseModel.Base,
                lenses: Sequence[str] | None = None) -> gtsam.NonlinearFactorGraph:
    """Landmarks seen by free poses and free intrinsics (``GeneralSFMFactor2`` of each view's lens model: Cal3DS2,
    Cal3Fisheye or Cal3Unified; all radtan when ``lenses`` is None)."""
    graph = gtsam.NonlinearFactorGraph()
    vs, js, meas = _observations(valid, pixels)
    factors = [_by_lens("GeneralSFMFactor2", lens) for lens in (lenses or [DEFAULT_LENS] * valid.shape[0])]
    for v, j, uv in zip(vs, js, meas, strict=True):
        graph.add(factors[v](uv, noise, view_pose_key(v), landmark_key(j), calib_key(v)))
    return graph


def rotation_gauge(calib: Calibration) -> tuple[int, int] | None:
    """(view, body rotation axis) held to remove the hidden rotation gauge (4): the pan (axis 1) of the view whose
    cx `principal_point_gauge` holds, or the tilt (axis 0) of the column neighbour in a single-column grid."""
    gauge = principal_point_gauge(calib)
    if gauge is None:
        return None
    return gauge[0], 1 if gauge[1] == 3 else 0


def holds_rotation_gauge(calib: Calibration, intrinsics_free: bool) -> bool:
    """Whether a MAP stage holds `rotation_gauge` (4): in a stereo pair only (``intrinsics_free`` is not a reason:
    holding the neighbour's pan *and* its cx exactly turned that view's real pan into a principal-point ramp over
    the grid — `--stages paper` wrote cx 20-30 px off after 1-degree knocks; the MAP priors split pan and cx)."""
    del intrinsics_free
    return calib.num_views == 2


def pose_priors(calib: Calibration, poses_free: bool, held_views: frozenset[int],
                scale_sigma_mm: float | None, map_centre: np.ndarray | None = None,
                map_sigmas: np.ndarray | None = None,
                intrinsics_free: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The pose rows of a `PriorTable` (mean (V, 4, 4), sigmas (V, 6)): the reference pose (gauge); held views and,
    when poses are not free, every view; on the free views either
    the MAP drift priors (``map_centre`` (V, 4, 4) ``ref_T_view`` of the input with ``map_sigmas`` (V, 6) in GTSAM's
    Pose3 tangent order, body frame: rotation about x, y (pan/tilt) and z (roll) in radians, then position in metres)
    or optional weak position priors (``scale_sigma_mm``, which bias rotations). With MAP
    priors and ``intrinsics_free`` the hidden rotation gauge (`rotation_gauge`) is held at the input."""
    n = calib.num_views
    mean = np.array(calib.ref_T_view, dtype=np.float64)
    sigmas = np.full((n, POSE_TANGENT), HELD_SIGMA)
    free = np.array([poses_free and v not in held_views and v != calib.grid.reference for v in range(n)])
    held = np.array([v in held_views and v != calib.grid.reference for v in range(n)])
    if map_centre is not None:  # held views stay at the centre
        mean[held] = np.asarray(map_centre)[held]
    if map_centre is not None and map_sigmas is not None:
        mean[free] = np.asarray(map_centre)[free]
        sigmas[free] = np.asarray(map_sigmas, dtype=np.float64)[free]
        rgauge = rotation_gauge(calib) if holds_rotation_gauge(calib, intrinsics_free) else None
        if rgauge is not None and free[rgauge[0]]:
            sigmas[rgauge[0], rgauge[1]] = HELD_SIGMA
    elif scale_sigma_mm is not None:
        sigmas[free] = [1.0, 1.0, 1.0, *(3 * [scale_sigma_mm * 1e-3])]
    else:
        sigmas[free] = np.nan  # free without a pull
    return mean, sigmas


def range_gauge(calib: Calibration) -> gtsam.NonlinearFactorGraph:
    """Scale: one range from the reference to the farthest view, at its calibrated length (pulls no direction)."""
    graph = gtsam.NonlinearFactorGraph()
    far = int(np.argmax(np.linalg.norm(calib.ref_T_view[:, :3, 3], axis=1)))
    graph.add(gtsam.RangeFactorPose3(view_pose_key(calib.grid.reference), view_pose_key(far),
                                     float(np.linalg.norm(calib.ref_T_view[far, :3, 3])),
                                     range_noise(RANGE_GAUGE_SIGMA_M)))
    return graph


def principal_point_gauge(calib: Calibration) -> tuple[int, int] | None:
    """(view, Cal3DS2 index) of the principal-point coordinate held to remove the hidden intrinsics gauge."""
    grid = calib.grid
    r0, c0 = grid.position(grid.reference)
    if grid.cols > 1:
        c = c0 + 1 if c0 + 1 < grid.cols else c0 - 1
        return grid.index(r0, c), 3  # cx
    if grid.rows > 1:
        r = r0 + 1 if r0 + 1 < grid.rows else r0 - 1
        return grid.index(r, c0), 4  # cy
    return None


def intrinsics_priors(calib: Calibration, held_views: frozenset[int], map_centre: Calibration | None = None,
                      map_sigmas: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The calibration rows of a `PriorTable` (mean, sigmas: V x `CAL_TANGENT_MAX`): fx, fy, cx, cy free for the
    non-reference, non-held views (minus the principal-point gauge); skew,
    distortion (each view's lens model's) and everything of the reference and held views held. With
    ``map_centre`` and ``map_sigmas`` (V, 4) the free ones get MAP drift priors centred on the input (fx, fy, cx, cy
    sigmas in px) instead of no pull."""
    n = calib.num_views
    mean = calibration_vectors(calib.intrinsics if map_centre is None else map_centre.intrinsics)
    sigmas = np.full(mean.shape, HELD_SIGMA)
    sigmas[:, 2] = MIN_SIGMA  # skew
    free = np.array([v != calib.grid.reference and v not in held_views for v in range(n)])
    focal_principal = [*CAL3DS2_INDICES[Group.FOCAL], *CAL3DS2_INDICES[Group.PRINCIPAL]]
    if map_centre is not None and map_sigmas is not None:
        # with MAP priors no principal point is held exactly: the drift priors fix the hidden gauge (2), and a
        # neighbour held at its input could not follow its own real pan (see `holds_rotation_gauge`)
        sigmas[np.ix_(free, focal_principal)] = np.asarray(map_sigmas, dtype=np.float64)[free]
    else:
        sigmas[np.ix_(free, focal_principal)] = FOCAL_FREE_SIGMA_PX
        gauge = principal_point_gauge(calib)
        if gauge is not None and free[gauge[0]]:
            sigmas[gauge] = HELD_SIGMA
    return mean, sigmas
