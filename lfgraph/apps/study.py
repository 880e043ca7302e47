"""Studies as a first-class, scalable, resumable workflow: the paper's shake experiment (Fig. "avg_synth") and
calibration accuracy against the number of frames.

A study is a list of seeded trials run on an executor (`lfgraph.core.executor`); every trial is a pure function of its
parameters, so the CSV is the same whatever executor ran it. Rows are written (atomically, sorted) after every
finished trial, and a re-run skips trials already in the CSV.
"""

from __future__ import annotations

import csv
import io
import logging
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lfgraph.core.files import write_text_atomic

FLOAT_FORMAT = "{:.6g}"  # CSV floats: enough for studies, and stable across executors


# --------------------------------------------------------------------------------------------- CSV
def _cell(x: Any) -> str:
    if isinstance(x, bool):
        return str(int(x))
    if isinstance(x, float | np.floating):
        return "nan" if not np.isfinite(x) else FLOAT_FORMAT.format(float(x))
    return str(x)


def write_rows(path: str | os.PathLike, rows: Sequence[dict[str, Any]], columns: Sequence[str],
               key: Callable[[dict[str, Any]], tuple]) -> None:
    """Write ``rows`` as CSV sorted by ``key``, atomically."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(columns)
    for row in sorted(rows, key=key):
        writer.writerow([_cell(row.get(c, "")) for c in columns])
    write_text_atomic(path, buf.getvalue())


def read_rows(path: str | os.PathLike, columns: Sequence[str]) -> list[dict[str, str]]:
    """Rows of an existing study CSV (strings); raises ValueError when its columns are not this study's."""
    p = Path(path)
    if not p.exists():
        return []
    with p.open(newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        if reader.fieldnames is None:
            return []
        if list(reader.fieldnames) != list(columns):
            raise ValueError(f"{p}: the CSV has columns {reader.fieldnames}, not this study's; choose another -o")
        rows, broken = [], []
        for row in reader:
            if None in row or any(row[c] is None for c in columns):  # cut short (fields missing) or extra fields
                broken.append(reader.line_num)
            else:
                rows.append(row)
    if broken:
        logging.getLogger("lfgraph").warning(f"{p}: ignoring {len(broken)} incomplete row(s) (line(s) "
                                             f"{', '.join(map(str, broken[:5]))}{' ...' if len(broken) > 5 else ''});"
                                             f" those trials run again")
    return rows


def run_study(trials: Sequence[Any], fn: Callable[[Any], list[dict[str, Any]]], out_csv: str | os.PathLike | None,
              columns: Sequence[str], trial_rows: Callable[[Any], set], row_key: Callable[[dict], tuple],
              executor_spec: str = "local", jobs: int | None = None, progress: bool = True,
              on_rows: Callable[[list[dict[str, Any]]], None] | None = None) -> list[dict[str, Any]]:
    """Run the trials not yet in ``out_csv`` and keep the CSV complete after every one (``out_csv`` None: every
    trial, rows kept in memory only).

    Returns:
        all rows (earlier ones as strings from the CSV, new ones as values).
    """
    from tqdm import tqdm

    from lfgraph.core.executor import open_executor

    existing = [] if out_csv is None else read_rows(out_csv, columns)
    try:
        done = {row_key(r) for r in existing}
    except (ValueError, TypeError) as exc:
        raise ValueError(f"{out_csv}: a row does not parse ({exc}); fix the file or choose another -o") from None
    todo = [t for t in trials if not trial_rows(t) <= done]
    # a trial that runs again replaces whatever part of its rows survived (a cut-short file)
    redo = set().union(*(trial_rows(t) for t in todo)) if todo else set()
    rows: list[dict[str, Any]] = [r for r in existing if row_key(r) not in redo]
    if not todo:
        return rows
    with open_executor(executor_spec, jobs) as ex, tqdm(total=len(trials), initial=len(trials) - len(todo),
                                                         desc="trials", unit="trial", disable=not progress) as bar:
        for _, new in ex.run(fn, todo):
            rows.extend(new)
            if out_csv is not None:
                write_rows(out_csv, rows, columns, key=row_key)
            if on_rows is not None:
                on_rows(new)
            bar.update()
    return rows


# --------------------------------------------------------------------------------------------- shake study
@dataclass(frozen=True)
class ShakeTrial:
    """One shaken rig and its frames, refined with every configuration: (label, `lfgraph.RefineConfig`) pairs."""

    scene: str
    level: int
    rot_deg: float
    trans_mm: float
    seed: int
    frames: int
    configs: tuple[tuple[str, Any], ...]


SHAKE_COLUMNS = ("scene", "config", "stages", "robust", "level", "rot_deg", "trans_mm", "seed", "frames", "landmarks",
                 "rms_before_px", "rms_after_px", "rot_err_before_deg", "rot_err_deg", "transfer_before_px",
                 "transfer_px", "pos_err_mm", "accepted")  # no wall times: the CSV must not depend on the executor


def shake_row_key(r: dict) -> tuple:
    """The key of a shake-study row (configuration, level, seed): what makes a trial's row unique in the CSV."""
    return (str(r["config"]), int(r["level"]), int(r["seed"]))


def shake_trial_rows(t: ShakeTrial) -> set[tuple]:
    """The row keys a shake trial produces (one per configuration)."""
    return {(label, t.level, t.seed) for label, _ in t.configs}


def run_shake_trial(trial: ShakeTrial) -> list[dict[str, Any]]:
    """Render the trial's frames with a shaken rig (in memory) and refine from the original with every config."""
    from lfgraph.datasets.rig import ShakeConfig, make_rig, shake_rig
    from lfgraph.datasets.scene import SceneConfig, make_scene, render_scene_views
    from lfgraph.datasets.scenes import get_scene
    from lfgraph.factors.noise import describe_noise
    from lfgraph.judge.evaluation import evaluate_calibration, transfer_error_at_infinity
    from lfgraph.refinement import refine
    from lfgraph.refinement.config import schedule_name

    named = get_scene(trial.scene)
    original = make_rig(named.rig, np.random.default_rng([trial.seed, 0]))
    truth = shake_rig(original, ShakeConfig(rot_deg=trial.rot_deg, trans_mm=trial.trans_mm),
                      np.random.default_rng([trial.seed, 1, trial.level])) \
        if trial.rot_deg or trial.trans_mm else original
    near, far = named.scene_depth_m
    cfg = SceneConfig(depth_m=(near, far), background_depth_m=far * 1.4)
    frames = []
    for f in range(trial.frames):
        scene = make_scene(cfg, np.random.default_rng([trial.seed, 2, f]))
        frames.append(render_scene_views(scene, truth, cfg, rngs=[np.random.default_rng([trial.seed, 3, f, v])
                                                                  for v in range(truth.num_views)]))

    def rot_rms(c) -> float:
        return float(np.sqrt(np.mean(evaluate_calibration(c, truth).rotation_deg ** 2)))

    def transfer(c) -> float:
        return float(np.sqrt(np.mean(transfer_error_at_infinity(c, truth) ** 2)))

    rows = []
    for label, config in trial.configs:
        try:
            refined, report = refine(original, frames, config)
            e = evaluate_calibration(refined, truth)
            result = {"landmarks": report.stages[-1].landmarks if report.stages else 0,
                      "rms_before_px": report.rms_before_px, "rms_after_px": report.rms_after_px,
                      "rot_err_deg": float(np.sqrt(np.mean(e.rotation_deg ** 2))), "transfer_px": transfer(refined),
                      "pos_err_mm": float(np.sqrt(np.mean(np.sum(e.position_mm ** 2, axis=1)))),
                      "accepted": report.accepted}
        except ValueError:  # no usable tracks: the trial failed to refine; record it, do not stop the study
            result = {"landmarks": 0, "rms_before_px": float("nan"), "rms_after_px": float("nan"),
                      "rot_err_deg": float("nan"), "transfer_px": float("nan"), "pos_err_mm": float("nan"),
                      "accepted": False}
        rows.append({"scene": trial.scene, "config": label, "stages": schedule_name(config.stages),
                     "robust": describe_noise(config.noise), "level": trial.level,
                     "rot_deg": trial.rot_deg, "trans_mm": trial.trans_mm, "seed": trial.seed,
                     "frames": trial.frames, "rot_err_before_deg": rot_rms(original),
                     "transfer_before_px": transfer(original), **result})
    return rows


def make_shake_trials(scene: str, rot_deg: Sequence[float], trans_mm: Sequence[float], trials: int, frames: int,
                      stages: Sequence[str], robust: Sequence[str], seed: int = 0) -> list[ShakeTrial]:
    """Paired shake levels (a single value broadcasts) x ``trials`` seeds; every trial runs every configuration."""
    rot, trans = list(rot_deg), list(trans_mm)
    if len(rot) == 1:
        rot = rot * len(trans)
    if len(trans) == 1:
        trans = trans * len(rot)
    if len(rot) != len(trans):
        raise ValueError(f"--rot-deg has {len(rot)} levels but --trans-mm {len(trans)}; give equal lists or one value")
    from lfgraph.refinement import RefineConfig

    configs = tuple((f"{s} / {r}", RefineConfig(stages=s, robust=r)) for s in stages for r in robust)
    return shake_trials(scene, rot, trans, trials, frames, configs, seed)


def shake_trials(scene: str, rot_deg: Sequence[float], trans_mm: Sequence[float], trials: int, frames: int,
                 configs: Sequence[tuple[str, Any]], seed: int = 0) -> list[ShakeTrial]:
    """Paired shake levels x ``trials`` seeds, each trial refined with every (label, RefineConfig)."""
    configs = tuple(configs)
    return [ShakeTrial(scene, k, float(rot_deg[k]), float(trans_mm[k]), seed + i, frames, configs)
            for k in range(len(rot_deg)) for i in range(trials)]


def _in_process_only(config) -> str | None:
    """Why ``config`` cannot run in another process (None when it can): GTSAM pickles a ``mEstimator.Custom`` without
    its Python functions (the copy raises "bad_function_call")."""
    import gtsam

    for noise in (config.noise, config.clean_noise):
        est = noise.robust() if isinstance(noise, gtsam.noiseModel.Robust) else noise
        if isinstance(est, gtsam.noiseModel.mEstimator.Custom):
            return "a gtsam mEstimator.Custom (its Python functions do not survive pickling)"
    return None


def shake_study(configs: Mapping[str, Any] | Sequence[Any], scene: str = "paper-5x5",
                rot_deg: Sequence[float] = (0.0, 0.25, 0.5, 1.0), trans_mm: Sequence[float] = (0.0, 1.0, 2.0, 5.0),
                trials: int = 3, frames: int = 4, out_csv: str | os.PathLike | None = None, executor: str = "local",
                jobs: int = 1, seed: int = 0, progress: bool = False) -> list[dict[str, Any]]:
    """The paper's shake study with any refinement configurations: every noise model (a kernel name, a
    `RobustKernel`, a GTSAM M-estimator or noise model), hooks, trackers, schedules.

    Each trial renders a named scene's rig knocked by one level (``rot_deg[k]`` degrees, ``trans_mm[k]`` mm; a
    single value broadcasts) with ``frames`` frames and refines it from the unknocked rig with every configuration.

    Args:
        configs: ``{label: RefineConfig}`` or a sequence of `RefineConfig` (labelled ``config 0``, ``config 1``, ...).
        out_csv: where the rows go, resumable (a re-run skips the trials already there); None keeps them in memory.
        executor, jobs: ``local`` with ``jobs`` processes (1: this process), ``dask-local`` or ``dask://HOST:PORT``.
            A ``mEstimator.Custom`` (Python callbacks) runs only in this process (``jobs=1``).

    Returns:
        one row per trial and configuration, with the columns of `SHAKE_COLUMNS` (errors against the knocked truth:
        ``rot_err_deg``, ``transfer_px``, ``pos_err_mm``; the input's ``rot_err_before_deg``, ``transfer_before_px``).

    Raises:
        TypeError: a configuration that is not a `RefineConfig`; ValueError: unequal level lists, a configuration
            that cannot leave this process with ``jobs > 1`` or another executor.
    """
    from lfgraph.refinement import RefineConfig

    labelled = list(configs.items()) if isinstance(configs, Mapping) else \
        [(f"config {i}", c) for i, c in enumerate(configs)]
    for label, config in labelled:
        if not isinstance(config, RefineConfig):
            raise TypeError(f"shake_study: configuration {label!r} must be a lfgraph.RefineConfig, got "
                            f"{type(config).__name__}")
        why = _in_process_only(config)
        if why is not None and not (executor == "local" and jobs == 1):
            raise ValueError(f"shake_study: configuration {label!r} uses {why}: run it with jobs=1 (this process)")
    rot, trans = list(rot_deg), list(trans_mm)
    rot, trans = (rot * len(trans), trans) if len(rot) == 1 else (rot, trans * len(rot) if len(trans) == 1 else trans)
    if len(rot) != len(trans):
        raise ValueError(f"rot_deg has {len(rot)} levels but trans_mm {len(trans)}; give equal lists or one value")
    trials_ = shake_trials(scene, rot, trans, trials, frames, labelled, seed)
    return run_study(trials_, run_shake_trial, out_csv, SHAKE_COLUMNS, shake_trial_rows, shake_row_key, executor,
                     jobs, progress=progress)


def summarise(rows: Sequence[dict[str, Any]], group: Sequence[str], x: str, metrics: Sequence[str]
              ) -> dict[tuple, dict[str, np.ndarray]]:
    """Mean of ``metrics`` per ``group`` and ``x`` value: {group values: {x: (X,), metric: (X,)}}."""
    out: dict[tuple, dict[str, list]] = {}
    for r in rows:
        g = tuple(str(r[k]) for k in group)
        out.setdefault(g, {})
        out[g].setdefault(float(r[x]), []).append([float(r[m]) for m in metrics])
    result = {}
    for g, by_x in out.items():
        xs = np.array(sorted(by_x))
        vals = np.array([np.nanmean(np.array(by_x[v]), axis=0) for v in xs])
        result[g] = {x: xs, **{m: vals[:, i] for i, m in enumerate(metrics)}}
    return result


def shake_plots(rows: Sequence[dict[str, Any]], out_csv: str | os.PathLike) -> list[Path]:
    """The shake study's figure beside the CSV (``<stem>.png`` and ``.pdf``): transfer error, rotation error and
    RMS against the shake, one series per configuration, median and spread over seeds (`lfgraph.viz.figures`)."""
    from lfgraph.viz.figures import shake_figure

    out = Path(out_csv)
    return shake_figure(rows, out.with_name(out.stem))


# --------------------------------------------------------------------------------------------- calibration study
@dataclass(frozen=True)
class CalibrationTrial:
    """One calibration-study trial: a named scene's rig shown ``frames`` board frames with corner noise ``sigma_px``
    (px), seeded by ``seed``."""
    scene: str
    frames: int
    sigma_px: float
    seed: int


CALIBRATION_COLUMNS = ("scene", "method", "frames", "sigma_px", "seed", "fx_err_px", "cx_err_px", "k1_err",
                       "pos_err_mm", "rot_err_deg")  # no wall times (executor-independent CSV)


def calibration_row_key(r: dict) -> tuple:
    """The key of a calibration-study row (method, frames, corner noise, seed)."""
    return (str(r["method"]), int(r["frames"]), float(r["sigma_px"]), int(r["seed"]))


CALIBRATION_METHODS = ("paper", "joint", "cramer-rao", "calibrateMultiview")


def calibration_trial_rows(t: CalibrationTrial) -> set[tuple]:
    """The row keys a calibration trial produces (one per method of `CALIBRATION_METHODS`)."""
    return {(m, t.frames, float(t.sigma_px), t.seed) for m in CALIBRATION_METHODS}


def run_calibration_trial(trial: CalibrationTrial) -> list[dict[str, Any]]:
    """Corner-only data: the paper route, the joint graph (+ its Cramér–Rao floor) and cv2.calibrateMultiview."""
    from lfgraph.core.calibration import Calibration
    from lfgraph.datasets.checkerboard import make_checkerboard_truth, make_corner_observations
    from lfgraph.datasets.rig import make_rig
    from lfgraph.datasets.scenes import get_scene
    from lfgraph.detect.detections import observations_from_arrays
    from lfgraph.judge.evaluation import evaluate_calibration
    from lfgraph.judge.peers import calibrate_multiview
    from lfgraph.pattern import calibrate_joint, calibrate_paper
    from lfgraph.pattern.initial import initial_board_T_ref

    named = get_scene(trial.scene)
    rng = np.random.default_rng(2024)  # the rig and board poses are the study's fixed scene
    truth_calib = make_rig(named.rig, rng)
    truth = make_checkerboard_truth(truth_calib, named.checkerboard, rng)
    corners, valid = make_corner_observations(truth, trial.sigma_px, np.random.default_rng(
        [trial.seed, int(round(trial.sigma_px * 1000)), trial.frames]))
    obs = observations_from_arrays(truth.board, truth_calib.grid, truth_calib.image_size_px, corners, valid)
    obs = obs.subset_frames(np.arange(min(trial.frames, obs.num_frames)))
    ref = truth_calib.grid.reference
    others = np.arange(truth_calib.num_views) != ref

    def errors(intr, poses) -> dict[str, float]:
        e = evaluate_calibration(Calibration(truth_calib.grid, truth_calib.image_size_px, intr, poses), truth_calib)
        return {"fx_err_px": float(np.sqrt(np.mean(e.intrinsics[:, 0] ** 2))),
                "cx_err_px": float(np.sqrt(np.mean(e.intrinsics[:, 2] ** 2))),
                "k1_err": float(np.sqrt(np.mean(e.intrinsics[:, 4] ** 2))),
                "pos_err_mm": float(np.sqrt(np.mean(np.sum(e.position_mm[others] ** 2, axis=1)))),
                "rot_err_deg": float(np.sqrt(np.mean(e.rotation_deg[others] ** 2)))}

    base = {"scene": trial.scene, "frames": obs.num_frames, "sigma_px": trial.sigma_px, "seed": trial.seed}
    rows = []
    paper = calibrate_paper(obs)
    rows.append({**base, "method": "paper", **errors(paper.intrinsics, paper.ref_T_view)})
    start = initial_board_T_ref(paper.view_T_board, paper.ref_T_view, obs.valid.sum(axis=2))
    joint = calibrate_joint(obs, paper.intrinsics, paper.ref_T_view, start)
    rows.append({**base, "method": "joint", **errors(joint.intrinsics, joint.ref_T_view)})
    s = joint.sigmas
    rows.append({**base, "method": "cramer-rao",
                 "fx_err_px": float(np.sqrt(np.mean([x["fx_px"] ** 2 for x in s]))),
                 "cx_err_px": float(np.sqrt(np.mean([x["cx_px"] ** 2 for x in s]))),
                 "k1_err": float(np.sqrt(np.mean([x["k1"] ** 2 for x in s]))),
                 "pos_err_mm": float(np.sqrt(np.mean([np.sum(np.square(x["position_mm"]))
                                                      for v, x in enumerate(s) if v != ref]))),
                 "rot_err_deg": float(np.sqrt(np.mean([np.sum(np.square(x["rotation_deg"]))
                                                       for v, x in enumerate(s) if v != ref])))})
    mv_intr, mv_poses = calibrate_multiview(obs)
    rows.append({**base, "method": "calibrateMultiview", **errors(mv_intr, mv_poses)})
    return rows


def calibration_plots(rows: Sequence[dict[str, Any]], out_csv: str | os.PathLike) -> list[Path]:
    """The calibration study's figure beside the CSV (``<stem>.png`` and ``.pdf``): per corner noise and metric,
    error against frames, one series per method, median and spread over seeds (`lfgraph.viz.figures`)."""
    from lfgraph.viz.figures import calibration_figure

    out = Path(out_csv)
    return calibration_figure(rows, out.with_name(out.stem))
