"""`calibrate`: the whole array from board observations, by the paper's route or the joint graph, scored the
same way (the **rig-consistent RMS** reprojects every observation through the one rig, board poses re-fitted with
the rig fixed, so inconsistency between views cannot hide in per-view figures)."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.grid_design import grid_problems
from lfgraph.core.observer import Observer, resolve, tell
from lfgraph.detect.board_order import order_symmetric_boards
from lfgraph.detect.detections import BoardObservations
from lfgraph.factors.board_graph import WEAK_FOCAL_SIGMA_REL, WEAK_PRINCIPAL_SIGMA_REL, WEAK_RADIAL_SIGMA
from lfgraph.factors.noise import RobustKernel
from lfgraph.lenses import lens_model
from lfgraph.pattern.config import CalibrateConfig, Init, Method
from lfgraph.pattern.design_check import mirrored_views
from lfgraph.pattern.initial import (
    CalibrationInputError,
    check_observations,
    design_initial,
    drop_view_frames,
    duplicate_view_frames,
    inconsistent_view_frames,
    initial_board_T_ref,
    weak_views,
)
from lfgraph.pattern.lenses import AUTO, LensChoice, choose_lenses, radial_profile_warning, resolve_lenses
from lfgraph.pattern.paper import calibrate_paper
from lfgraph.pattern.schedule import BoardRun, joint_schedule
from lfgraph.pattern.scoring import (
    CalibrationReport,
    coverage_map,
    coverage_warnings,
    fit_board_poses,
    outlier_frames,
    rig_residuals,
    rms_px,
)


def _without_copies(obs: BoardObservations, say: Observer) -> tuple[BoardObservations, list[str]]:
    """``obs`` without boards that repeat an earlier frame's (`duplicate_view_frames`), and the warning naming them."""
    duplicates = duplicate_view_frames(obs)
    if not duplicates:
        return obs, []
    obs = drop_view_frames(obs, [(v, f) for v, f, _ in duplicates])
    message = ("boards identical to an earlier frame's (copied images?) were left out: "
               + ", ".join(f"{obs.describe(v, f)} = frame {obs.frame_names[g]}" for v, f, g in duplicates[:10])
               + (f" and {len(duplicates) - 10} more" if len(duplicates) > 10 else ""))
    say.log(message)
    check_observations(obs)
    return obs, [message]


def _lens_choice(obs: BoardObservations, config: CalibrateConfig, say: Observer) -> LensChoice:
    """Each view's lens model: as named in ``config.lens``, the ``auto`` ones chosen (and the table logged)."""
    requested = resolve_lenses(config.lens, obs.grid)
    if AUTO not in requested:
        return LensChoice(requested, {}, {})
    choice = choose_lenses(obs, requested)
    say.log(choice.table(obs.grid))
    return choice


def _board_order(obs: BoardObservations, say: Observer) -> tuple[BoardObservations, list[str]]:
    """A symmetric board's corner order made consistent (`order_symmetric_boards`: the detector cannot tell a board
    turned by 180° from the original; the rig's geometry can), with its warnings; other boards unchanged."""
    if not obs.board.is_symmetric:
        return obs, []
    obs, order = order_symmetric_boards(obs)
    if order.reversed.any():
        say.log(f"symmetric board: corner order reversed in {int(order.reversed.sum())} view-frame(s) so that "
                f"every view agrees with the rig")
    return obs, list(order.messages)


def _paper_route(obs: BoardObservations, choice: LensChoice, say: Observer,
                 keep: bool = False) -> tuple[BoardObservations, Any, list[str]]:
    """The paper route (`calibrate_paper`, reusing the lens choice's Zhang fits). One bad view-frame (a mis-detected
    board, another camera's image) skews the PnP average the rig starts from and then the whole fit: view-frames
    whose relative pose contradicts the other frames' are dropped and the route runs again. With ``keep`` (a robust
    joint fit follows, which screens every view-frame on the whole rig: `_joint_route`) they are left out of this
    route only, the joint fit's start, and kept for the joint graph to judge: a per-view fit of a wide lens on a board
    covering part of its field can put a PnP pose of exact corners 1-3 deg off. The joint graph starts where the
    pairs' Levenberg–Marquardt ends: from the PnP averages alone its screening fit settled elsewhere on caliscope's
    out-of-sync webcams (held-out 1.316 -> 1.337 px). Returns (observations, its result, one warning per dropped)."""
    lenses = choice.lenses
    paper = calibrate_paper(obs, lenses, choice.mono)
    bad = inconsistent_view_frames(paper.view_T_board, obs.grid.reference)
    if not bad:
        return obs, paper, []
    reduced = drop_view_frames(obs, [(v, f) for v, f, _, _ in bad])
    check_observations(reduced)
    warnings = []
    for v, f, rot, pos in bad:
        what = f"{obs.describe(v, f)}: its board pose contradicts the rig the other frames agree on (off by " \
               f"{rot:.2f} deg, {1e3 * pos:.1f} mm)"
        if keep:
            say.log(f"{what}: left out of the start; the joint fit's screen judges it on the whole rig")
        else:
            warnings.append(f"{what}: dropped from the calibration")
            say.log(warnings[-1])
    return (obs if keep else reduced), calibrate_paper(reduced, lenses), warnings


def _joint_route(obs: BoardObservations, paper, lenses, config: CalibrateConfig,
                 say: Observer) -> tuple[BoardObservations, Any, list[str]]:
    """The joint graph (`calibrate_joint`), started from the paper route or from design values, as two steps of the
    one stage schedule (`lfgraph.pattern.schedule`: the screen, then the reported fit). Robust by default:
    a Cauchy fit first finds suspect view-frames (swapped or mislabelled images, a mis-detected board, which plain
    least squares would smear over every view), and those the rest of the rig cannot predict either are dropped by
    name (`lfgraph.pattern.screen`: a merely weakly constrained view-frame is kept); the least-squares fit (the
    reported one) starts from the robust result when the screen dropped any, else from the start (the fit without the
    screen). A view the robust fit misses in more than a quarter of its frames keeps them (a systematic misfit, said).
    Returns (observations, its result, warnings)."""
    if paper is not None:
        start_intr, start_poses, view_T_board = paper.intrinsics, paper.ref_T_view, paper.view_T_board  # noqa: N806
    else:
        start_intr, start_poses, view_T_board = design_initial(obs, config.focal_px, config.pitch_m)  # noqa: N806
        start_intr = tuple(i.with_distortion(lens) for i, lens in zip(start_intr, lenses, strict=True))
    start_boards = initial_board_T_ref(view_T_board, start_poses, obs.valid.sum(axis=2))
    run = joint_schedule(BoardRun(obs, start_intr, start_poses, start_boards), config, _screens(config), say)
    return run.obs, run.joint, list(run.dropped)


def _screens(config: CalibrateConfig) -> bool:
    """Whether the joint route screens view-frames with a robust fit first (`screen_view_frames`): by default; not
    when the user chose the noise model."""
    return config.screen and isinstance(config.noise, RobustKernel) and config.noise.name == "none"


def _weak_view_warnings(obs: BoardObservations, joint) -> list[str]:
    """One warning per view that saw the board in too few frames (calibrated through the rig, with a prior)."""
    out = []
    for v in np.nonzero(weak_views(obs))[0]:
        s = joint.sigmas[v] if joint.sigmas is not None else None
        sig = "" if s is None else (f"; 1-sigma fx {s['fx_px']:.2g} px, cx {s['cx_px']:.2g} px, position "
                                    f"{max(s['position_mm']):.2g} mm, rotation {max(s['rotation_deg']):.2g} deg")
        out.append(f"{obs.describe(int(v))} saw the board in only {int(obs.seen[v].sum())} frame(s): "
                   f"calibrated through the rig with a prior on its intrinsics (focal length "
                   f"±{100 * WEAK_FOCAL_SIGMA_REL:g} %, principal point ±{100 * WEAK_PRINCIPAL_SIGMA_REL:g} % "
                   f"of the width, k1, k2 ±{WEAK_RADIAL_SIGMA:g}){sig}; show it the board more often")
    return out


def _result_warnings(obs: BoardObservations, intrinsics, res: np.ndarray, frame_rms: np.ndarray,
                     outliers: list[int], cells: np.ndarray) -> list[str]:
    """Warnings about a calibration's residuals: outlying frames, a radial residual pattern per view (a lens model
    that does not fit), and views the board did not cover."""
    warnings = []
    if outliers:
        warnings.append("frames with outlying reprojection error (check these images for a mis-detected board): "
                        + ", ".join(f"{obs.frame_names[f]} ({frame_rms[f]:.3f} px)" for f in outliers))
    for v in range(obs.num_views):
        message = radial_profile_warning(obs, v, intrinsics[v], res[v])
        if message:
            warnings.append(message)
    return warnings + coverage_warnings(obs, cells)


def _result(obs: BoardObservations, method, init, paper, joint, intrinsics, ref_T_view: np.ndarray,  # noqa: N803
            boards: np.ndarray, res: np.ndarray, warnings: list[str], seconds: dict[str, float],
            choice) -> tuple[Calibration, CalibrationReport]:
    """The calibration and its report from a route's result: RMS per view and frame, outlying frames, the
    residual and coverage warnings, the figures in ``metrics``."""
    n_views = obs.num_views
    view_rms = np.asarray(rms_px(res, axis=(1, 2)))
    frame_rms = np.asarray(rms_px(res, axis=(0, 2)))
    rig_rms = float(rms_px(res, axis=None))
    outliers = outlier_frames(frame_rms)
    cells = coverage_map(obs)
    warnings += _result_warnings(obs, intrinsics, res, frame_rms, outliers, cells)
    report = CalibrationReport(
        method=str(method), init=None if method == Method.PAPER else str(init),
        e_mono_px=None if paper is None else paper.e_mono_px, e_pnp_px=None if paper is None else paper.e_pnp_px,
        view_e_mono_px=np.full(n_views, np.nan) if paper is None else paper.view_e_mono_px,
        view_e_pnp_px=np.full(n_views, np.nan) if paper is None else paper.view_e_pnp_px,
        rig_rms_px=rig_rms, view_rms_px=view_rms, frame_rms_px=frame_rms, outlier_frames=tuple(outliers),
        coverage=cells.mean(axis=(1, 2)), coverage_cells=cells, frames_per_view=obs.seen.sum(axis=1),
        noise_sigma_px=None if joint is None else joint.noise_sigma_px,
        sigmas=None if joint is None else joint.sigmas,
        optimization=None if joint is None else joint.optimization, warnings=tuple(warnings), seconds=seconds,
        board_T_ref=boards, residuals_px=res)
    metrics = {**report.metrics(), **choice.metrics()}
    calib = Calibration(obs.grid, obs.image_size_px, intrinsics, ref_T_view, None, metrics, obs.view_image_sizes_px)
    return calib, report


def _held_against_the_grid(obs: BoardObservations, ref_T_view: np.ndarray, config: CalibrateConfig,  # noqa: N803
                           say: Observer) -> list[str]:
    """Refuse a calibration that contradicts its grid (`grid_problems`, unless ``config.check_grid`` is off);
    returns its notes as warnings."""
    errors, notes = grid_problems(obs.grid, ref_T_view)
    if errors and config.check_grid:
        raise CalibrationInputError("; ".join(errors) + " (a rig that is deliberately no grid: check_grid=False, "
                                    "--no-grid-check)")
    for note in notes:
        say.log(note)
    return errors + notes


def calibrate(obs: BoardObservations, config: CalibrateConfig | None = None,
              observer: Observer | None = None) -> tuple[Calibration, CalibrationReport]:
    """Calibrate the array from board observations.

    Args:
        obs: corners of every view and frame (`lfgraph.detect_capture`).
        config: method, start and options (`CalibrateConfig()` by default: the joint graph started from the paper
            route).
        observer: hears one log line per route and every optimiser iteration (`lfgraph.core.observer`); default: log
            lines go to `logging`.

    Returns:
        the calibration (its ``metrics`` hold the report's figures) and the report.

    Raises:
        CalibrationInputError: views without enough board detections, views that share no frames with others.
    """
    if not isinstance(obs, BoardObservations):
        raise TypeError(f"calibrate: obs must be lfgraph.BoardObservations (from lfgraph.detect_capture or "
                        f"lfgraph.load_detections), got {type(obs).__name__}")
    if config is not None and not isinstance(config, CalibrateConfig):
        raise TypeError(f"calibrate: config must be a lfgraph.CalibrateConfig, got {type(config).__name__}")
    config = config or CalibrateConfig()
    say = resolve(observer)
    tell(say, "run_start", "calibrate", None)
    method, init = config.method, config.init
    check_observations(obs)
    obs, duplicate_warnings = _without_copies(obs, say)
    obs, order_warnings = _board_order(obs, say)
    seconds: dict[str, float] = {}
    warnings: list[str] = duplicate_warnings + order_warnings
    t0 = time.perf_counter()
    choice = _lens_choice(obs, config, say)
    lenses = choice.lenses
    seconds["lens_choice"] = time.perf_counter() - t0
    if config.tangential and not any(lens_model(lens).tangential for lens in lenses):
        warnings.append(f"tangential distortion asked for, but every view's lens ({', '.join(sorted(set(lenses)))}) "
                        f"has none: it changes nothing")
    paper = None
    if method == Method.PAPER or init == Init.PAPER:
        t0 = time.perf_counter()
        obs, paper, dropped = _paper_route(obs, choice, say, keep=method != Method.PAPER and _screens(config))
        seconds["paper"] = time.perf_counter() - t0
        warnings += dropped + list(paper.warnings)
        mirrored = mirrored_views(obs, paper.view_T_board, lenses)
        if mirrored:
            raise CalibrationInputError("; ".join(mirrored))
        say.log(f"paper route: E_mono {paper.e_mono_px:.4f} px, E_PnP "
            f"{'-' if paper.e_pnp_px is None else f'{paper.e_pnp_px:.4f}'} px ({seconds['paper']:.1f} s)")
    joint = None
    if method == Method.PAPER:
        intrinsics, ref_T_view = paper.intrinsics, paper.ref_T_view  # noqa: N806
        t0 = time.perf_counter()
        boards = fit_board_poses(intrinsics, ref_T_view, obs,
                                 initial_board_T_ref(paper.view_T_board, ref_T_view, obs.valid.sum(axis=2)))
        seconds["rig_fit"] = time.perf_counter() - t0
        res = rig_residuals(intrinsics, ref_T_view, boards, obs)
    else:
        t0 = time.perf_counter()
        obs, joint, dropped = _joint_route(obs, paper, lenses, config, say)
        warnings += dropped
        seconds["joint"] = time.perf_counter() - t0
        opt = joint.optimization
        say.log(f"joint route: {opt.iterations} LM iterations, error {opt.initial_error:.4g} -> "
                f"{opt.final_error:.4g} ({seconds['joint']:.1f} s incl. marginals)")
        intrinsics, ref_T_view = joint.intrinsics, joint.ref_T_view  # noqa: N806
        warnings += _weak_view_warnings(obs, joint)
        res = joint.residuals_px
        boards = joint.board_T_ref
    warnings += _held_against_the_grid(obs, ref_T_view, config, say)
    calib, report = _result(obs, method, init, paper, joint, intrinsics, ref_T_view, boards, res, warnings, seconds,
                            choice)
    tell(say, "run_end", "calibrate", None, calib, report, obs)  # e.g. a rerun recording shows the result
    return calib, report
