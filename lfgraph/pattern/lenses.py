"""Per-view lens models in pattern calibration: one view's calibration under a given model (``cv2.calibrateCamera``
for radtan, ``cv2.fisheye.calibrate`` for fisheye, a one-view joint graph for unified, started from the fisheye fit),
board poses under any model, and the automatic choice: the model that predicts held-out frames best (k-fold over the
view's frames), with a radial-residual check of the one kept."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from lfgraph.core.camera import Intrinsics
from lfgraph.core.geometry import invert_T, make_T, rotation_from_rotvec
from lfgraph.core.grid import ViewGrid
from lfgraph.core.parallel import thread_map
from lfgraph.detect.detections import BoardObservations
from lfgraph.lenses import FISHEYE, RADTAN, UNIFIED, lens_model, lens_names
from lfgraph.pattern.config import AUTO_LENS, CalibrateConfig, parse_lens_spec
from lfgraph.pattern.joint import calibrate_joint
from lfgraph.pattern.pose_fit import board_pose

AUTO = AUTO_LENS
FIT_LENSES = (RADTAN, FISHEYE)  # the candidates of --lens auto; unified is fitted when named (a board determines its
# xi only weakly: `lfgraph.factors.board_graph.UNIFIED_XI_SIGMA`; on OpenCV's eight wide real views its held-out error
# was at best 0.2 % below fisheye's, 64 % above on one, in ~10x the time: README, "Lens models")
FIT_ERRORS = (cv2.error, RuntimeError)  # OpenCV's calibration failed, or GTSAM's graph (unified) could not be solved
UNIFIED_START_XI = 1.0  # unified from a fisheye fit: xi = 1 maps angle theta to 2 tan(theta / 2) ...
UNIFIED_START_FOCAL_SCALE = 2.0  # ... so its focal length starts at twice the fisheye's (equal near the centre)
MONO_FLAGS = cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST  # the paper's model: k1, k2, no tangential, no skew
FISHEYE_FLAGS = cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW
FISHEYE_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
# a fisheye fit's fallback start (`_fisheye_calibrate`): the equidistant lens, k1..k4 held at 0
EQUIDISTANT_FLAGS = cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_FIX_K4
HELDOUT_FOLDS = 8  # k of the k-fold held-out-frame error (every frame is held out once)
SIMPLER_MARGIN = 0.02  # a model richer than radtan is kept only if it predicts held-out frames >= 2 % better ...
SIMPLER_MIN_GAIN_PX = 0.005  # ... and by >= 0.005 px (noise-free data: both models fit to ~0)
RADIAL_BINS = 6  # radial residual profile: rings of equal width out to the farthest corner
RADIAL_SIGNIFICANCE = 4.0  # a ring's mean radial residual beyond this many standard errors ...
RADIAL_MIN_PX = 0.05  # ... and this size is a structured residual the model leaves
# --lens auto fits a fisheye model only to a view whose radtan fit leaves a ring beyond this many standard errors
# (no size limit): models that differ only in their radial function cannot differ "clearly" (`_clearly_better`) on
# residuals without radial structure, and a fisheye fit costs ~6x a radtan one (paper-4x4: 0.54 vs 0.09 s per view)
RADIAL_STRUCTURE_SIGNIFICANCE = 3.0


class LensSpecError(ValueError):
    """A lens choice that names an unknown model or view."""


def resolve_lenses(spec: str | Mapping[str | int, str], grid: ViewGrid) -> tuple[str, ...]:
    """Each view's requested model (`LENSES` or ``auto``) from ``"auto"``, one model name, a mapping of view names
    (``r00_c01``) or indices to models, or the CLI's ``"auto,r00_c02=fisheye"`` (a default, then per-view ones)."""
    try:
        default, per_view = parse_lens_spec(spec)
    except (TypeError, ValueError) as exc:
        raise LensSpecError(str(exc)) from None
    choices = (AUTO, *lens_names())
    out = [default] * grid.num_views
    seen: dict[int, str | int] = {}
    for key, lens in per_view.items():
        v = grid.find(key, "lens", LensSpecError)
        if v in seen:  # the same view by name and by index
            raise LensSpecError(f"lens: view {grid.name(v)} given more than once ({seen[v]!r} and {key!r})")
        seen[v] = key
        if lens not in choices:
            raise LensSpecError(f"lens for {key}: unknown model {lens!r}; choose from {', '.join(choices)}")
        out[v] = lens
    return tuple(out)


@dataclass(frozen=True)
class MonoFit:
    """One view calibrated alone: intrinsics, RMS (px, Euclidean per corner) and ``view_T_board`` per fitted frame."""

    intrinsics: Intrinsics
    rms_px: float
    view_T_board: dict[int, np.ndarray]


def _view_points(obs: BoardObservations, v: int, frames: Sequence[int]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    obj = obs.board.object_points()
    objs = [obj[obs.valid[v, f]].astype(np.float64) for f in frames]
    imgs = [obs.corners_px[v, f][obs.valid[v, f]].astype(np.float64) for f in frames]
    return objs, imgs


def fitter_name(lens: str) -> str:
    """What calibrates one view of model ``lens`` alone (`fit_mono`), for messages."""
    return {"pinhole": "OpenCV's calibrateCamera", "fisheye": "OpenCV's fisheye.calibrate"}.get(
        lens_model(lens).opencv, f"the {lens} one-view graph")


def fit_mono(obs: BoardObservations, v: int, lens: str, frames: Sequence[int] | None = None,
             guess: Intrinsics | None = None) -> MonoFit:
    """Calibrate view ``v`` alone under ``lens`` from ``frames`` (default: every frame it saw), started from
    ``guess`` when given (OpenCV's ``CALIB_USE_INTRINSIC_GUESS``; its own initialisation otherwise).

    Raises:
        cv2.error: OpenCV's calibration failed; RuntimeError: GTSAM's unified graph could not be solved (callers
            decide what that means; `FIT_ERRORS` holds both).
    """
    frames = [int(f) for f in (np.nonzero(obs.seen[v])[0] if frames is None else frames)]
    opencv = lens_model(lens).opencv  # what fits it alone: OpenCV's pinhole or fisheye calibration, else a graph
    if opencv is None:
        return _fit_unified(obs, v, frames, guess)
    objs, imgs = _view_points(obs, v, frames)
    size = obs.image_size(v)
    use_guess = guess is not None and guess.lens == lens
    if opencv == "fisheye":
        K, D, rvecs, tvecs = _fisheye_calibrate(objs, imgs, size, guess if use_guess else None)  # noqa: N806
        intr = Intrinsics.from_opencv(K, D.ravel(), lens=lens)
    else:
        _, K, dist, rvecs, tvecs = cv2.calibrateCamera(  # noqa: N806
            [o.astype(np.float32) for o in objs], [i.astype(np.float32) for i in imgs], size,
            guess.K if use_guess else None, guess.dist_cv.copy() if use_guess else None,
            flags=MONO_FLAGS | (cv2.CALIB_USE_INTRINSIC_GUESS if use_guess else 0))
        intr = Intrinsics.from_opencv(K, np.concatenate([dist.ravel()[:4], [0.0]]), lens=lens)
    poses = {f: make_T(rotation_from_rotvec(np.ravel(r)), np.ravel(t)) for f, r, t in zip(frames, rvecs, tvecs,
                                                                                            strict=True)}
    T = np.concatenate([np.broadcast_to(poses[f], (len(o), 4, 4)) for f, o in zip(frames, objs, strict=True)])  # noqa: N806
    cam = np.einsum("nij,nj->ni", T[:, :3, :3], np.concatenate(objs)) + T[:, :3, 3]
    sq = np.sum((intr.project(cam) - np.concatenate(imgs)) ** 2, axis=1)
    return MonoFit(intr, float(np.sqrt(np.mean(sq))), poses)


def _fisheye_calibrate(objs: list[np.ndarray], imgs: list[np.ndarray], size: tuple[int, int],
                       guess: Intrinsics | None) -> tuple[np.ndarray, np.ndarray, tuple, tuple]:
    """``cv2.fisheye.calibrate`` of one view (K, D, rvecs, tvecs), started from ``guess`` or OpenCV's own start; when
    that fails, once more from the equidistant fit (k1..k4 held at 0, then freed). OpenCV's fisheye iteration has no
    step control: a step can leave the undistortion's range, and `InitExtrinsics` then asserts on a NaN. On hetero1's
    2048x2048 fisheye (OpenCV's multiview test data) it did so in 25 of 180 fits of corners moved by +-1 ulp (3-30 %
    per set of frames, measured), so whether fisheye was chosen hung on the corners' last bits; from the equidistant
    fit, 0 of 180, at the same minimum (RMS equal to 6 digits).

    Raises:
        cv2.error: both fits failed (the first one's error).
    """
    objs3, imgs2 = [o.reshape(1, -1, 3) for o in objs], [i.reshape(1, -1, 2) for i in imgs]

    def fit(K, D, flags):  # noqa: N803
        return cv2.fisheye.calibrate(objs3, imgs2, size, K, D, flags=FISHEYE_FLAGS | flags,
                                     criteria=FISHEYE_CRITERIA)[1:]

    try:
        return fit(guess.K, guess.dist_cv.copy(), cv2.CALIB_USE_INTRINSIC_GUESS) if guess is not None \
            else fit(None, None, 0)
    except cv2.error as first:
        try:
            K, D, _, _ = fit(None, None, EQUIDISTANT_FLAGS)  # noqa: N806
            return fit(K, np.zeros_like(D), cv2.CALIB_USE_INTRINSIC_GUESS)
        except cv2.error:
            raise first from None


def _fit_unified(obs: BoardObservations, v: int, frames: list[int], guess: Intrinsics | None) -> MonoFit:
    """View ``v`` alone under the unified model: a one-view joint graph (`calibrate_joint`), started from ``guess``
    (a unified fit) or from the fisheye fit (`UNIFIED_START_XI`, `UNIFIED_START_FOCAL_SCALE`, its board poses)."""
    fish = fit_mono(obs, v, FISHEYE, frames)
    if guess is not None and guess.lens == UNIFIED:
        start = guess
    else:
        f = fish.intrinsics
        start = Intrinsics(UNIFIED_START_FOCAL_SCALE * f.fx, UNIFIED_START_FOCAL_SCALE * f.fy, f.cx, f.cy, 0.0, 0.0,
                           xi=UNIFIED_START_XI, lens=UNIFIED)
    keep = np.zeros(obs.num_frames, dtype=bool)
    keep[frames] = True
    one = BoardObservations(obs.board, ViewGrid(1, 1, 0), obs.image_size(v), obs.corners_px[v:v + 1],
                            obs.valid[v:v + 1] & keep[None, :, None], obs.frame_names)
    board_T_ref = np.full((obs.num_frames, 4, 4), np.nan)  # noqa: N806
    for fr, pose in fish.view_T_board.items():
        board_T_ref[fr] = invert_T(pose)
    joint = calibrate_joint(one, (start,), np.eye(4)[None], board_T_ref, CalibrateConfig(marginals=False))
    poses = {fr: invert_T(joint.board_T_ref[fr]) for fr in frames}
    objs, imgs = _view_points(obs, v, frames)
    intr = joint.intrinsics[0]
    sq = [np.sum((intr.project(o @ T[:3, :3].T + T[:3, 3]) - i) ** 2, axis=1) for o, i, T in
          zip(objs, imgs, (poses[fr] for fr in frames), strict=True)]
    return MonoFit(intr, float(np.sqrt(np.mean(np.concatenate(sq)))), poses)


def heldout_rms_px(obs: BoardObservations, v: int, lens: str, folds: int = HELDOUT_FOLDS,
                   min_train: int = 3, start: Intrinsics | None = None) -> float:
    """RMS error (px) of view ``v``'s held-out frames under ``lens``: k-fold over its frames, each fold calibrated
    from the others (started from ``start``, the fit to all frames, when given) and scored on its own frames with
    only the board pose fitted. NaN with too few frames; inf when a fit fails."""
    frames = np.nonzero(obs.seen[v])[0]
    k = min(folds, len(frames))
    if len(frames) - int(np.ceil(len(frames) / max(k, 1))) < min_train or k < 2:
        return float("nan")
    obj = obs.board.object_points()
    sq: list[np.ndarray] = []
    for i in range(k):
        test = frames[i::k]
        try:
            fit = fit_mono(obs, v, lens, [f for f in frames if f not in set(test)], start)
        except FIT_ERRORS:
            return float("inf")
        for f in test:
            m = obs.valid[v, f]
            T = board_pose(fit.intrinsics, obj[m], obs.corners_px[v, f][m])  # noqa: N806
            if T is None:
                return float("inf")
            pred = fit.intrinsics.project(obj[m] @ T[:3, :3].T + T[:3, 3])
            sq.append(np.sum((pred - obs.corners_px[v, f][m]) ** 2, axis=1))
    err = np.concatenate(sq)
    return float(np.sqrt(np.mean(err))) if np.all(np.isfinite(err)) else float("inf")


@dataclass(frozen=True)
class LensChoice:
    """What `choose_lenses` decided: each view's model, and per candidate model and view the RMS (px) of the fit to
    the view's own frames and of its held-out frames (NaN where not computed, inf where OpenCV's fit failed)."""

    lenses: tuple[str, ...]
    fit_px: dict[str, np.ndarray]
    heldout_px: dict[str, np.ndarray]
    mono: dict[tuple[int, str], MonoFit] = field(default_factory=dict, compare=False, repr=False)  # (view, lens) fits

    def metrics(self) -> dict[str, Any]:
        """``{"lens_choice": {"fit_px": ..., "heldout_px": ...}}`` for ``calibration.json`` (None where not computed);
        empty when no model was chosen (all named)."""
        if not self.heldout_px:
            return {}
        return {"lens_choice": {name: {lens: [None if not np.isfinite(x) else float(x) for x in values]
                                       for lens, values in table.items()}
                                for name, table in (("fit_px", self.fit_px), ("heldout_px", self.heldout_px))}}

    def table(self, grid: ViewGrid) -> str:
        """The comparison as printed by ``calibrate``."""
        def cell(x: float) -> str:
            return "failed" if np.isinf(x) else ("-" if np.isnan(x) else f"{x:.4f}")

        names = list(self.heldout_px)
        lines = ["lens model per view (RMS px of the view's own frames / of held-out frames; * kept):",
                 "  view     " + "".join(f"{n:>22}" for n in names)]
        for v, kept in enumerate(self.lenses):
            cells = [f"{cell(self.fit_px[n][v]) + ' / ' + cell(self.heldout_px[n][v]) + '*' * (n == kept):>22}"
                     for n in names]
            lines.append(f"  {grid.name(v):<9}" + "".join(cells))
        return "\n".join(lines)


def _clearly_better(rich: float, simple: float) -> bool:
    return rich < (1.0 - SIMPLER_MARGIN) * simple and rich < simple - SIMPLER_MIN_GAIN_PX


def _preferred(heldout: dict[str, np.ndarray], v: int) -> str:
    """The model view ``v`` keeps: going from the simplest (`FIT_LENSES` order), a richer one replaces the kept one
    only where it predicts held-out frames clearly better (a model whose score is missing counts as no better)."""
    kept = RADTAN if np.isfinite(heldout[RADTAN][v]) else None
    for lens in FIT_LENSES[1:]:
        score = heldout[lens][v]
        if np.isfinite(score) and (kept is None or _clearly_better(score, heldout[kept][v])):
            kept = lens
    return kept or RADTAN


def _fit_rms(obs: BoardObservations, v: int, lens: str, into: dict[str, np.ndarray],
             starts: dict[str, Intrinsics], mono: dict[tuple[int, str], MonoFit]) -> float:
    try:
        fit = fit_mono(obs, v, lens)
        into[lens][v], starts[lens], mono[v, lens] = fit.rms_px, fit.intrinsics, fit
    except FIT_ERRORS:
        into[lens][v] = float("inf")
    return float(into[lens][v])


def choose_lenses(obs: BoardObservations, requested: Sequence[str]) -> LensChoice:
    """Each ``auto`` view's model: of the `FIT_LENSES` candidates, radtan unless fisheye predicts held-out frames
    clearly better (`SIMPLER_MARGIN` and `SIMPLER_MIN_GAIN_PX`). When radtan leaves no radial structure
    (`RADIAL_STRUCTURE_SIGNIFICANCE`) it is kept without a fisheye fit (its figures shown as ``-``); when fisheye
    does not even fit the view's own frames clearly better, radtan is kept without cross-validation (held-out errors
    shown as ``-``). Views
    with too few frames to hold any out take the model most of the other views chose (radtan on a tie). Named
    models are kept as given."""
    n = obs.num_views
    table = {lens: np.full(n, np.nan) for lens in FIT_LENSES}
    fits = {lens: np.full(n, np.nan) for lens in FIT_LENSES}
    lenses = list(requested)
    mono: dict[tuple[int, str], MonoFit] = {}
    undecided = []
    weak = obs.seen.sum(axis=1) < 3

    def choose(v: int) -> str | None:  # view v's model, None when undecided (one thread per view: their own cells)
        starts: dict[str, Intrinsics] = {}
        if not weak[v]:
            base = _fit_rms(obs, v, RADTAN, fits, starts, mono)
            if (v, RADTAN) in mono and not _radial_structure(obs, v, mono[v, RADTAN]):
                return RADTAN
            if not _clearly_better(_fit_rms(obs, v, FISHEYE, fits, starts, mono), base):
                return RADTAN
        for lens in FIT_LENSES:
            table[lens][v] = heldout_rms_px(obs, v, lens, start=starts.get(lens))
        if not np.any(np.isfinite([table[lens][v] for lens in FIT_LENSES])):
            return None
        return _preferred(table, v)

    auto = [v for v in range(n) if requested[v] == AUTO]
    for v, lens in zip(auto, thread_map(choose, auto), strict=True):
        if lens is None:
            undecided.append(v)
        else:
            lenses[v] = lens
    decided = [lens for v, lens in enumerate(lenses) if lens != AUTO]
    common = max(FIT_LENSES, key=lambda lens: (decided.count(lens), lens == RADTAN)) if decided else RADTAN
    for v in undecided:
        lenses[v] = common
    return LensChoice(tuple(lenses), fits, table, mono)


def _rings(obs: BoardObservations, v: int, intr: Intrinsics, residuals_px: np.ndarray) -> list[tuple[float, ...]]:
    """View ``v``'s mean radial residual per ring of corners (by distance from the principal point, `RADIAL_BINS`
    rings of equal width): (mean px, its standard error, inner and outer radius px) of each ring of 10 corners or
    more; empty with fewer than 10 corners per ring on average. ``residuals_px``: (F, C, 2), observed - predicted."""
    m = obs.valid[v] & np.all(np.isfinite(residuals_px), axis=-1)
    if m.sum() < 10 * RADIAL_BINS:
        return []
    d = obs.corners_px[v][m] - [intr.cx, intr.cy]
    r = np.hypot(d[:, 0], d[:, 1])
    radial = np.sum(residuals_px[m] * d, axis=1) / np.maximum(r, 1e-9)
    edges = np.linspace(0.0, r.max() * (1 + 1e-9), RADIAL_BINS + 1)
    ring = np.digitize(r, edges) - 1
    return [(float(sel.mean()), float(sel.std(ddof=1) / np.sqrt(len(sel))), edges[b], edges[b + 1])
            for b, sel in ((b, radial[ring == b]) for b in range(RADIAL_BINS)) if len(sel) >= 10]


def _radial_structure(obs: BoardObservations, v: int, fit: MonoFit) -> bool:
    """Whether the one-view fit leaves a ring `RADIAL_STRUCTURE_SIGNIFICANCE` standard errors off (or too few
    corners to tell)."""
    obj = obs.board.object_points()
    res = np.full(obs.corners_px[v].shape, np.nan)
    for f, T in fit.view_T_board.items():  # noqa: N806
        m = obs.valid[v, f]
        res[f, m] = obs.corners_px[v, f][m] - fit.intrinsics.project(obj[m] @ T[:3, :3].T + T[:3, 3])
    rings = _rings(obs, v, fit.intrinsics, res)
    return not rings or any(abs(mean) > RADIAL_STRUCTURE_SIGNIFICANCE * se for mean, se, _, _ in rings)


def radial_profile_warning(obs: BoardObservations, v: int, intr: Intrinsics, residuals_px: np.ndarray) -> str | None:
    """A warning when view ``v``'s residuals (F, C, 2; observed - predicted) keep a radial pattern: a ring of
    corners (by distance from the principal point) whose mean radial residual is `RADIAL_SIGNIFICANCE` standard
    errors and `RADIAL_MIN_PX` away from 0 — the lens model does not fit this lens."""
    worst = None
    for mean, se, lo, hi in _rings(obs, v, intr, residuals_px):
        if abs(mean) > max(RADIAL_SIGNIFICANCE * se, RADIAL_MIN_PX) and (worst is None or abs(mean) > abs(worst[0])):
            worst = (mean, lo, hi)
    if worst is None:
        return None
    return (f"{obs.describe(v)}: the {intr.lens} lens model leaves a radial residual of {worst[0]:+.3f} px at "
            f"{worst[1]:.0f}-{worst[2]:.0f} px from the principal point: try another model (--lens "
            f"{obs.grid.name(v)}=" + (FISHEYE if intr.lens == RADTAN else RADTAN) + ")")
