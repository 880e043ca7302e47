"""Per-view lens models in pattern calibration: one view's calibration under a given model (``cv2.calibrateCamera``
for radtan, ``cv2.fisheye.calibrate`` for fisheye), board poses under any model, and the automatic choice: the model
that predicts held-out frames best (k-fold over the view's frames), with a radial-residual check of the one kept."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from lfgraph.camera import FISHEYE, LENSES, RADTAN, Intrinsics
from lfgraph.detections import BoardObservations
from lfgraph.geometry import make_T, rotation_from_rotvec
from lfgraph.grid import ViewGrid

AUTO = "auto"
FIT_LENSES = (RADTAN, FISHEYE)  # the models pattern calibration fits (the joint board graph's factors)
MONO_FLAGS = cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST  # the paper's model: k1, k2, no tangential, no skew
FISHEYE_FLAGS = cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW
FISHEYE_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
HELDOUT_FOLDS = 8  # k of the k-fold held-out-frame error (every frame is held out once)
SIMPLER_MARGIN = 0.02  # a model richer than radtan is kept only if it predicts held-out frames >= 2 % better ...
SIMPLER_MIN_GAIN_PX = 0.005  # ... and by >= 0.005 px (noise-free data: both models fit to ~0)
POSE_ITERATIONS = 8  # Gauss-Newton steps of a held-out board pose in distorted pixels
RADIAL_BINS = 6  # radial residual profile: rings of equal width out to the farthest corner
RADIAL_SIGNIFICANCE = 4.0  # a ring's mean radial residual beyond this many standard errors ...
RADIAL_MIN_PX = 0.05  # ... and this size is a structured residual the model leaves


class LensSpecError(ValueError):
    """A lens choice that names an unknown model or view."""


def resolve_lenses(spec: str | Mapping[str | int, str], grid: ViewGrid) -> tuple[str, ...]:
    """Each view's requested model (`LENSES` or ``auto``) from ``"auto"``, one model name, a mapping of view names
    (``r00_c01``) or indices to models, or the CLI's ``"auto,r00_c02=fisheye"`` (a default, then per-view ones)."""
    default, per_view = AUTO, {}
    if isinstance(spec, str):
        for token in (t.strip() for t in spec.split(",") if t.strip()):
            if "=" in token:
                name, _, lens = token.partition("=")
                per_view[name.strip()] = lens.strip()
            else:
                default = token
    elif isinstance(spec, Mapping):
        per_view = dict(spec)
    else:
        raise LensSpecError(f"lens must be a model name or a mapping of views to models, got {type(spec).__name__}")
    choices = (AUTO, *LENSES)
    if default not in choices:
        raise LensSpecError(f"unknown lens {default!r}; choose from {', '.join(choices)}")
    out = [default] * grid.num_views
    for key, lens in per_view.items():
        v = grid.find(key, "lens", LensSpecError)
        if lens not in choices:
            raise LensSpecError(f"lens for {key}: unknown model {lens!r}; choose from {', '.join(choices)}")
        out[v] = lens
    unfit = sorted({lens for lens in out if lens not in (AUTO, *FIT_LENSES)})
    if unfit:
        raise LensSpecError(f"pattern calibration fits {', '.join(FIT_LENSES)} lenses; {', '.join(unfit)} is read, "
                            f"written, rectified and exported but not yet estimated from a board")
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


def fit_mono(obs: BoardObservations, v: int, lens: str, frames: Sequence[int] | None = None,
             guess: Intrinsics | None = None) -> MonoFit:
    """Calibrate view ``v`` alone under ``lens`` from ``frames`` (default: every frame it saw), started from
    ``guess`` when given (OpenCV's ``CALIB_USE_INTRINSIC_GUESS``; its own initialisation otherwise).

    Raises:
        cv2.error: OpenCV's calibration failed (callers decide what that means).
    """
    frames = [int(f) for f in (np.nonzero(obs.seen[v])[0] if frames is None else frames)]
    objs, imgs = _view_points(obs, v, frames)
    size = obs.size_of(v)
    use_guess = guess is not None and guess.lens == lens
    if lens == FISHEYE:
        _, K, D, rvecs, tvecs = cv2.fisheye.calibrate(  # noqa: N806
            [o.reshape(1, -1, 3) for o in objs], [i.reshape(1, -1, 2) for i in imgs], size,
            guess.K if use_guess else None, guess.dist_cv.copy() if use_guess else None,
            flags=FISHEYE_FLAGS | (cv2.CALIB_USE_INTRINSIC_GUESS if use_guess else 0), criteria=FISHEYE_CRITERIA)
        intr = Intrinsics.from_opencv(K, D.ravel(), lens=FISHEYE)
    else:
        _, K, dist, rvecs, tvecs = cv2.calibrateCamera(  # noqa: N806
            [o.astype(np.float32) for o in objs], [i.astype(np.float32) for i in imgs], size,
            guess.K if use_guess else None, guess.dist_cv.copy() if use_guess else None,
            flags=MONO_FLAGS | (cv2.CALIB_USE_INTRINSIC_GUESS if use_guess else 0))
        intr = Intrinsics.from_opencv(K, np.concatenate([dist.ravel()[:4], [0.0]]))
    poses = {f: make_T(rotation_from_rotvec(np.ravel(r)), np.ravel(t)) for f, r, t in zip(frames, rvecs, tvecs,
                                                                                            strict=True)}
    sq = [np.sum((intr.project(o @ T[:3, :3].T + T[:3, 3]) - i) ** 2, axis=1) for o, i, T in
          zip(objs, imgs, (poses[f] for f in frames), strict=True)]
    return MonoFit(intr, float(np.sqrt(np.mean(np.concatenate(sq)))), poses)


def board_pose(intr: Intrinsics, obj: np.ndarray, px: np.ndarray) -> np.ndarray | None:
    """``view_T_board`` (4, 4) of one board under any lens model: PnP on the undistorted corners, then Gauss-Newton
    on the distorted pixel error. None when the corners cannot be undistorted or PnP fails."""
    xy = intr.undistort(px)
    ok = np.all(np.isfinite(xy), axis=1)
    if ok.sum() < 4:
        return None
    try:
        found, rvec, tvec = cv2.solvePnP(obj[ok].astype(np.float64), xy[ok], np.eye(3), None,
                                         flags=cv2.SOLVEPNP_ITERATIVE)
    except cv2.error:
        return None
    if not found:
        return None
    x = np.concatenate([np.ravel(rvec), np.ravel(tvec)])

    def residual(p: np.ndarray) -> np.ndarray:
        R = rotation_from_rotvec(p[:3])  # noqa: N806
        return (intr.project(obj @ R.T + p[3:]) - px).ravel()

    for _ in range(POSE_ITERATIONS):
        r = residual(x)
        if not np.all(np.isfinite(r)):
            break
        eps = 1e-7 * np.maximum(1.0, np.abs(x))
        J = np.stack([(residual(x + e) - r) / h for e, h in zip(np.diag(eps), eps, strict=True)], axis=1)  # noqa: N806
        if not np.all(np.isfinite(J)):
            break
        step = np.linalg.lstsq(J, -r, rcond=None)[0]
        if np.sum(residual(x + step) ** 2) >= np.sum(r**2):
            break
        x = x + step
    return make_T(rotation_from_rotvec(x[:3]), x[3:])


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
        except cv2.error:
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


def _fit_rms(obs: BoardObservations, v: int, lens: str, into: dict[str, np.ndarray],
             starts: dict[str, Intrinsics]) -> float:
    try:
        fit = fit_mono(obs, v, lens)
        into[lens][v], starts[lens] = fit.rms_px, fit.intrinsics
    except cv2.error:
        into[lens][v] = float("inf")
    return float(into[lens][v])


def choose_lenses(obs: BoardObservations, requested: Sequence[str]) -> LensChoice:
    """Each ``auto`` view's model: the `FIT_LENSES` candidate with the lowest held-out-frame RMS, radtan unless a
    richer model is clearly better (`SIMPLER_MARGIN` and `SIMPLER_MIN_GAIN_PX`). A richer model that does not even
    fit the view's own frames clearly better is not cross-validated (its held-out error is shown as ``-``). Views
    with too few frames to hold any out take the model most of the other views chose (radtan on a tie). Named
    models are kept as given."""
    n = obs.num_views
    table = {lens: np.full(n, np.nan) for lens in FIT_LENSES}
    fits = {lens: np.full(n, np.nan) for lens in FIT_LENSES}
    lenses = list(requested)
    undecided = []
    weak = obs.seen.sum(axis=1) < 3
    for v in range(n):
        if requested[v] != AUTO:
            continue
        starts: dict[str, Intrinsics] = {}
        if not weak[v]:
            base = _fit_rms(obs, v, RADTAN, fits, starts)
            if not any([_clearly_better(_fit_rms(obs, v, lens, fits, starts), base) for lens in FIT_LENSES
                        if lens != RADTAN]):
                lenses[v] = RADTAN
                continue
        for lens in FIT_LENSES:
            table[lens][v] = heldout_rms_px(obs, v, lens, start=starts.get(lens))
        scores = np.array([table[lens][v] for lens in FIT_LENSES])
        if not np.any(np.isfinite(scores)):
            undecided.append(v)
            continue
        best = FIT_LENSES[int(np.nanargmin(np.where(np.isfinite(scores), scores, np.inf)))]
        base = table[RADTAN][v]
        if best != RADTAN and np.isfinite(base) and not _clearly_better(table[best][v], base):
            best = RADTAN
        lenses[v] = best
    decided = [lens for v, lens in enumerate(lenses) if lens != AUTO]
    common = max(FIT_LENSES, key=lambda lens: (decided.count(lens), lens == RADTAN)) if decided else RADTAN
    for v in undecided:
        lenses[v] = common
    return LensChoice(tuple(lenses), fits, table)


def radial_profile_warning(obs: BoardObservations, v: int, intr: Intrinsics, residuals_px: np.ndarray) -> str | None:
    """A warning when view ``v``'s residuals (F, C, 2; observed - predicted) keep a radial pattern: a ring of
    corners (by distance from the principal point) whose mean radial residual is `RADIAL_SIGNIFICANCE` standard
    errors and `RADIAL_MIN_PX` away from 0 — the lens model does not fit this lens."""
    m = obs.valid[v] & np.all(np.isfinite(residuals_px), axis=-1)
    if m.sum() < 10 * RADIAL_BINS:
        return None
    d = obs.corners_px[v][m] - [intr.cx, intr.cy]
    r = np.hypot(d[:, 0], d[:, 1])
    radial = np.sum(residuals_px[m] * d, axis=1) / np.maximum(r, 1e-9)
    edges = np.linspace(0.0, r.max() * (1 + 1e-9), RADIAL_BINS + 1)
    ring = np.digitize(r, edges) - 1
    worst = None
    for b in range(RADIAL_BINS):
        sel = radial[ring == b]
        if len(sel) < 10:
            continue
        mean, se = float(sel.mean()), float(sel.std(ddof=1) / np.sqrt(len(sel)))
        if abs(mean) > max(RADIAL_SIGNIFICANCE * se, RADIAL_MIN_PX) and (worst is None or abs(mean) > abs(worst[0])):
            worst = (mean, edges[b], edges[b + 1])
    if worst is None:
        return None
    return (f"{obs.describe(v)}: the {intr.lens} lens model leaves a radial residual of {worst[0]:+.3f} px at "
            f"{worst[1]:.0f}-{worst[2]:.0f} px from the principal point: try another model (--lens "
            f"{obs.grid.name(v)}=" + (FISHEYE if intr.lens == RADTAN else RADTAN) + ")")
