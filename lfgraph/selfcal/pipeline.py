"""`calibrate_scene`: a camera array's intrinsics and poses from design values and ordinary scene frames."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterable

import gtsam
import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.observer import Observer, resolve
from lfgraph.core.sigmas import Sigmas
from lfgraph.engine.schedule import TrackState
from lfgraph.engine.triangulate import project_views
from lfgraph.factors.selfcal_graph import design_tangent_sigmas
from lfgraph.lenses import lens_model
from lfgraph.selfcal.config import Design, SelfCalConfig
from lfgraph.selfcal.pinned import SceneFit, fit_pins, mode_rows, pin_warnings, weak_modes, zoom_of
from lfgraph.selfcal.pins import PIN_TYPES, DistancePin, PinError
from lfgraph.selfcal.report import GAUGES, Mode, SelfCalReport, modes
from lfgraph.selfcal.retrack import retrack
from lfgraph.selfcal.scatter import mode_pulls, robust_joint, track_sandwich
from lfgraph.selfcal.solve import drop_outliers, initial_landmarks, posterior, zoom_to_prior
from lfgraph.selfcal.stages import (
    SelfCalibrationError,
    depths_suffice,
    final_fit,
    final_free,
    measured_noise,
    run_stages,
    with_depth,
)
from lfgraph.selfcal.tracks import PooledTracks, measure_coverage, pool_tracks

# re-tracked observations whose window mismatch exceeds this multiple of the median are dropped. Measured on
# paper-4x4 (4 frames, exact correspondences): error RMS of those kept (below 1 px) 0.143 px with all, 0.104 px
# (91 % kept) at 2x, 0.082 px (80 %) at 1.5x, 0.066 px (68 %) at 1.25x
MISMATCH_FACTOR = 1.5
# the re-tracking runs with the staged calibration's local maps, then again with the final fit's (`_final`)
RETRACK_PASSES = 2
SECOND_PASS_MIN_SHARE = 0.5  # ... kept only when it keeps at least this share of the first pass's tracks: on a 2x2
# of 10 mm pitch with scenes at 3-4 m (small-2x2, 6 frames) the final fit's maps matched 228 of 1578, and its final
# stage kept none (the first pass's fit is good there)


def _retracked(tracks: PooledTracks, points: np.ndarray, calib: Calibration,
               say: Observer) -> tuple[PooledTracks, np.ndarray, int, np.ndarray]:
    """The tracks followed again from the reference view with windows warped by ``calib`` (it knows how each view
    scales, turns and bends the reference window; translation-only KLT is biased by that): the kept tracks, their
    landmarks, how many observations were re-tracked and (K,) the kept tracks' columns in ``tracks``.

    A window that still differs from the reference's after the warp (a depth edge, a slanted surface, little
    contrast) tracks badly: only re-tracked observations that match about as well as the typical one are kept.
    Observations not re-tracked (windows keeping under `MIN_WINDOW_SHARE` inside the image, ~2 px from its border;
    failed fits) are dropped too: their chain positions carry the scale bias the re-tracking removes."""
    grid = calib.grid
    pixels, valid, done, mismatch = retrack(tracks.pixels, tracks.valid, tracks.patches, calib, points)
    retracked = int(done.sum())
    ref_view = np.arange(grid.num_views)[:, None] == grid.reference
    limit = MISMATCH_FACTOR * float(np.median(mismatch[done])) if retracked else np.inf
    valid = valid & (ref_view | (done & (mismatch <= limit)))
    pixels = np.where(valid[..., None], pixels, np.nan)
    tracks = PooledTracks(pixels, valid, tracks.frame, tracks.frames_seen, tracks.frames_used, tracks.patches)
    keep = drop_outliers(calib, tracks.pixels, tracks.valid, points)[0] & (valid.sum(axis=0) >= 2)
    tracks, points = tracks.subset(keep), points[keep]
    say.log(f"self-calibration: {retracked} observations re-tracked with the calibrated local maps, "
            f"{tracks.num_tracks} tracks kept")
    return tracks, points, retracked, np.nonzero(keep)[0]


def _final(state: TrackState, nominal: Calibration, free: frozenset, sigmas: Sigmas, design: Design,
           config: SelfCalConfig, say: Observer):
    """The re-tracking (with ``config.retrack``) and the final stage (`final_fit`) from the staged ``state``:
    (the state, graph, values, the noise used, the final stage's `StageResult`s, observations re-tracked).

    The staged calibration holds the near-gauges at the design (`selfcal_graph.intrinsics_gauges`) and leaves its
    landmarks where the hidden principal-point gauge put them (paper-4x4 seed 5: at a tenth of their depth, the
    local maps' scale 0.1-0.45 % off across the grid); windows warped by those maps are biased in a way the final
    stage reads as a zoom (+4.1 px from the flat-surface tracks alone, 0.6 px with the final fit's maps). So the
    chain tracks are re-tracked once more with the final fit's maps (`RETRACK_PASSES`), and fitted again."""
    chain, points, calib = state.tracks, state.points, state.calib
    retracked, passes_out = 0, []
    use_retrack = config.retrack and chain.patches is not None
    # a wide lens's angles pin its focal length: no zoom valley to leave the staged landmarks off their depth (and on
    # the rendered fisheye 2x2 a second pass left the transfer at infinity 0.25 px against 0.11 px with one)
    passes = RETRACK_PASSES if use_retrack and not lens_model(nominal.intrinsics[0].lens).wide else 1
    done = None  # the last pass's (state, graph, values, noise used, observations re-tracked)
    for k in range(passes):
        start = state
        if use_retrack:
            kept, kept_points, retracked, columns = _retracked(chain, points, calib, say)
            if k and kept.num_tracks < SECOND_PASS_MIN_SHARE * done[0].tracks.num_tracks:
                say.log(f"self-calibration: re-tracked again, {kept.num_tracks} of the {done[0].tracks.num_tracks} "
                        "tracks match: the first pass's fit is kept")
                break
            start = TrackState.start(calib, kept.pixels, kept.valid, kept_points, kept)
        noise = measured_noise(start.errors(), start.tracks.num_tracks, calib.num_views, free)
        if {"focal", "distortion"} <= free:  # the zoom is an exact gauge only with the distortion free to follow it
            zoom_calib, zoomed = zoom_to_prior(start.calib, start.points, nominal.intrinsics[0])
            start = dataclasses.replace(start, calib=zoom_calib, points=zoomed)
        try:
            state, graph, values, used_noise, passes = final_fit(start, nominal, free, sigmas, noise, design, config,
                                                                 say)
        except SelfCalibrationError as exc:
            if done is None:
                raise
            say.log(f"self-calibration: the fit after re-tracking again failed ({exc}): the first pass's fit is kept")
            break
        done = (state, graph, values, used_noise, retracked)
        passes_out += passes
        if use_retrack:  # the next pass: the chain tracks the fit kept, its calibration and landmarks
            chain, points, calib = chain.subset(columns[state.index]), state.points, state.calib
    state, graph, values, used_noise, retracked = done
    return state, graph, values, used_noise, passes_out, retracked


def _posterior(scene: SceneFit, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
               config: SelfCalConfig, say: Observer) -> tuple[Calibration, Sigmas, list[Mode], tuple, SceneFit]:
    """The posterior of the scene's final fit, or with ``config.pins`` that of the pinned fit (`_pinned`):
    (calibration, posterior, modes, one `PinResult` per pin, the scene fit with its zoom and sigma)."""
    grid = scene.calib.grid
    distortion = "distortion" in scene.free
    post, cameras = posterior(graph, values, scene.calib.lenses, poses=True)
    joint = _track_robust(scene, values, cameras, say)
    post = post.with_calibration_cov(joint, scene.calib.lenses)  # per view as widened: a view's fx carries the zoom
    zoom, sigma = zoom_of(scene.calib, joint, scene.sigmas, distortion)
    mode_values, mode_cov = weak_modes(scene.calib, joint)
    scene = dataclasses.replace(scene, zoom_px=zoom, zoom_sigma_px=sigma, modes=mode_values, modes_cov=mode_cov)
    if not config.pins:
        return scene.calib, post, modes(joint, design_tangent_sigmas(scene.sigmas)[grid.reference], grid,
                                        distortion), (), scene
    return (*_pinned(scene, config, say), scene)


def _track_robust(scene: SceneFit, values: gtsam.Values, cameras: np.ndarray, say: Observer) -> np.ndarray:
    """The (DV, DV) covariance of every view's calibration from the final fit's ``cameras`` covariance (calibrations,
    then poses), its weak modes widened to how the tracks' residuals scatter (`lfgraph.selfcal.scatter`)."""
    calib, tracks = scene.calib, scene.tracks
    n_cal = len(cameras) - 6 * calib.num_views
    rows = mode_rows(calib.grid, calib.num_views, n_cal // calib.num_views)
    pulls = mode_pulls(calib, values, scene.points, tracks.valid, cameras, rows)
    residuals = np.where(tracks.valid[..., None], tracks.pixels - project_views(calib, scene.points), 0.0)
    assumed, seen = track_sandwich(pulls, np.nan_to_num(residuals), scene.noise_px)
    joint = robust_joint(cameras[:n_cal, :n_cal], rows, assumed, seen)
    before, after = (float(np.sqrt(rows[0] @ c @ rows[0])) for c in (cameras[:n_cal, :n_cal], joint))
    say.log(f"self-calibration: the zoom's sigma {before:.3g} px from the graph, {after:.3g} px with the tracks' "
            "own scatter (used)")
    return joint


def _pinned(scene: SceneFit, config: SelfCalConfig, say: Observer) -> tuple[Calibration, Sigmas, list[Mode], tuple]:
    """The pins' fit from the scene's optimum (`fit_pins`: each pin tested against the scene first) and its
    posterior: (calibration, posterior, modes, one `PinResult` per pin)."""
    grid = scene.calib.grid
    distortion = "distortion" in scene.free
    calib, _, graph, values, results = fit_pins(scene, config.pins, distortion, config.graph_hooks, say)
    post, joint = posterior(graph, values, calib.lenses)
    return calib, post, modes(joint, design_tangent_sigmas(scene.sigmas)[grid.reference], grid, distortion), results


def pin_scene(report: SelfCalReport, design: Design, pins, config: SelfCalConfig | None = None,
              observer: Observer | None = None) -> tuple[Calibration, SelfCalReport]:
    """Pins added to a finished self-calibration: the final stage of ``report``'s scene fit with the pins' factors,
    without tracking or solving the scene again (what `calibrate_tracks` does with ``config.pins``).

    Args:
        report: a `calibrate_tracks` or `calibrate_scene` report (it keeps its scene fit).
        pins: `BoardPin`, `DistancePin` (followed into the views: `DistancePin.followed`) or `ViewPin` values.

    Raises:
        PinRefused: a pin disagrees with the scene beyond their sigmas (named).
        PinError: a pin cannot be used.
    """
    if report.scene is None:
        raise ValueError("pin_scene needs the report of a self-calibration run (its scene fit)")
    config = dataclasses.replace(config or SelfCalConfig(), pins=tuple(pins) if not isinstance(pins, PIN_TYPES)
                                 else (pins,))
    start = time.perf_counter()
    calib, post, mode_list, results = _pinned(report.scene, config, resolve(observer))
    seconds = {**report.seconds, "pins": time.perf_counter() - start}
    out = dataclasses.replace(report, posterior=post, modes=tuple(mode_list), pins=results, seconds=seconds,
                              warnings=report.warnings + tuple(pin_warnings(results)))
    return calib.replace(metrics=_metrics(design, out, out.noise_px, post)), out


def _metrics(design: Design, report: SelfCalReport, noise_px: float, post) -> dict:
    """What a self-calibration stores in ``Calibration.metrics``."""
    return {"source": "self-calibration from scene frames (lfgraph calibrate-scene)", "scale_from": "design pitch",
            "design": {"rows": design.rows, "cols": design.cols, "pitch_mm": design.pitch_mm,
                       "focal_px": design.focal_px},
            "selfcal_rms_px": report.rms_px, "selfcal_noise_px": noise_px, "verdict": report.verdict,
            "zoom_from": report.zoom_from,
            "sigmas": post.to_metrics()}  # the one writer (`Sigmas`), as calibrate writes them


NO_TRACK = ("no track was followed through all {views} views in {frames} frame(s); use textured scenes that every "
            "view sees")


def calibrate_tracks(tracks: PooledTracks, design: Design, config: SelfCalConfig | None = None,
                     observer: Observer | None = None) -> tuple[Calibration, SelfCalReport]:
    """Self-calibrate from pooled tracks (the solver of `calibrate_scene`; tests feed it exact synthetic tracks): the
    staged MAP steps on the one schedule (`lfgraph.selfcal.stages.run_stages`), the re-tracking, the final
    least-squares stage at the noise its residuals support (`final_fit`), the posterior and the pins.

    Raises:
        SelfCalibrationError: the tracks cannot determine the parameters (the message says what is missing).
    """
    config = config or SelfCalConfig()
    say = resolve(observer)
    start = time.perf_counter()
    nominal = design.calibration()
    sigmas = config.sigmas(design)
    grid = nominal.grid
    if tracks.num_tracks == 0:
        raise SelfCalibrationError(NO_TRACK.format(views=grid.num_views, frames=tracks.frames_seen))
    points = initial_landmarks(nominal, tracks.pixels, tracks.valid)
    state = with_depth(TrackState.start(nominal, tracks.pixels, tracks.valid, points, tracks), design)
    state, staged = run_stages(state, nominal, sigmas, design, config, say)
    stages, warnings = list(staged.stages), list(staged.warnings)
    # final stage: plain least squares at the measured noise, so that the marginals are the posterior. The noise
    # is the residuals' RMS per coordinate (with the degrees of freedom), not a robust estimate: KLT errors have
    # heavy tails, and the marginals of a least-squares fit scale with the RMS (a MAD-based sigma was 0.5x of it)
    free = final_free(stages, config)
    state, graph, values, used_noise, passes, retracked = _final(state, nominal, free, sigmas, design, config, say)
    stages += passes
    calib, points, tracks = state.calib, state.points, state.tracks
    coverage = measure_coverage(calib, tracks, points, design.focal_px, design.pitch_mm / 1000.0)
    depths_suffice(coverage)
    calib, post, mode_list, pins, scene = _posterior(
        SceneFit(calib, nominal, points, tracks, free, sigmas, used_noise, 0.0, 0.0), graph, values, config, say)
    if coverage.missing_regions():
        warnings.append(f"no tracks in every view in: {', '.join(coverage.missing_regions())}")
    warnings += pin_warnings(pins)
    report = SelfCalReport(coverage, tuple(stages), used_noise, stages[-1].rms_px, post, tuple(mode_list),
                           staged.distortion, tuple(warnings), {"graph": time.perf_counter() - start}, GAUGES,
                           retracked, tracks, pins, scene)
    say.log(f"self-calibration: rms {report.rms_px:.3f} px at a measured noise of {used_noise:.3f} px; verdict "
            f"{report.verdict}")
    return calib.replace(metrics=_metrics(design, report, used_noise, post)), report


def _keeping(frames: Iterable[np.ndarray], kept: dict) -> Iterable[np.ndarray]:
    """``frames`` as they are read, keeping those whose index is a key of ``kept`` (a distance pin's frame)."""
    for f, images in enumerate(frames):
        if f in kept:
            kept[f] = np.asarray(images)
        yield images


def _followed(pin, kept: dict, design: Design):
    """A distance pin marked in one view followed into every view of its frame (other pins unchanged).

    Raises:
        PinError: its frame was not read (fewer frames, or beyond ``max_frames``)."""
    if not (isinstance(pin, DistancePin) and pin.needs_images):
        return pin
    if kept.get(pin.frame) is None:
        raise PinError(f"pin {pin.name}: frame {pin.frame} was not read (frames are counted from 0 among those "
                       f"used)")
    return pin.followed(kept[pin.frame], design.grid)


def calibrate_scene(frames: Iterable[np.ndarray], design: Design, config: SelfCalConfig | None = None,
                    observer: Observer | None = None) -> tuple[Calibration, SelfCalReport]:
    """Calibrate a camera array without a target: from its design values and ordinary textured scene frames.

    Starts from the ideal grid (parallel views at the nominal pitch, principal points at the image centre, the
    nominal focal length and distortion), tracks features through the grid in every frame (chain KLT, as the
    refinement does), and grows a MAP solution in stages (`SelfCalConfig.stages`), each freeing more parameter
    groups pulled to their design values with the design tolerances. Gauges: the reference view's pose; scale from
    the design pitch; the hidden principal-point gauge and the common zoom from the priors (see the report's modes).

    Args:
        frames: (V, H, W) uint8 grayscale views of each frame (e.g. ``open_capture(path, grid).frames()``); use
            many frames at varied depths with texture across the whole image.
        design: the design values.
        config: options (`SelfCalConfig()` by default).
        observer: hears log lines and every optimiser iteration.

    Returns:
        the calibration (its ``metrics`` say that scale comes from the design pitch, and hold the sigmas) and the
        report (coverage, stages, posterior sigmas, weakly seen modes, verdict).

    Raises:
        SelfCalibrationError: the frames cannot determine the parameters (too few frames or tracks, too narrow a
            depth range, image regions without texture); the message says what is missing.
    """
    config = config or SelfCalConfig()
    t0 = time.perf_counter()
    marked = {p.frame: None for p in config.pins if isinstance(p, DistancePin) and p.needs_images}
    tracks = pool_tracks(_keeping(frames, marked), design.grid, design.image_size_px, config.tracks_per_frame,
                         config.tracker, config.max_frames, keep_patches=config.retrack)
    if marked:
        config = dataclasses.replace(config, pins=tuple(_followed(p, marked, design) for p in config.pins))
    seconds = time.perf_counter() - t0
    calib, report = calibrate_tracks(tracks, design, config, observer)
    return calib, SelfCalReport(**{**report.__dict__, "seconds": {"tracking": seconds, **report.seconds}})
