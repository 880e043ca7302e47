"""What a refinement measured: per-stage and overall reports."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lfgraph.core.verdict import Verdict
from lfgraph.engine.schedule import StageFigures

OK, DRIFTED, UNCERTAIN, REFERENCE = Verdict.OK, Verdict.DRIFTED, Verdict.UNCERTAIN, Verdict.REFERENCE
VERDICTS = (OK, DRIFTED, UNCERTAIN, REFERENCE)  # a view's verdict (`lfgraph.refinement.assess.ViewVerdict`)


@dataclass(frozen=True)
class StageReport(StageFigures):
    """One stage: the schedule's figures (`StageFigures`: landmarks used, RMS before/after (px), iterations, seconds),
    and the per-view changes it made."""

    rotation_change_deg: np.ndarray
    position_change_mm: np.ndarray
    focal_change_px: np.ndarray
    principal_change_px: np.ndarray


@dataclass(frozen=True)
class RefinementReport:
    """Everything `refine` measured: per-frame track counts after each filter, per-stage reports, and the RMS of
    the tracks kept by the last pass with the input and with the refined calibration."""

    frame_counts: tuple[dict[str, int], ...]
    frame_rms_before_px: tuple[float, ...]
    stages: tuple[StageReport, ...]
    frames_used: int
    stop_reason: str
    rms_before_px: float
    rms_after_px: float
    seconds: float
    seconds_matching: float = 0.0
    seconds_adjustment: float = 0.0
    accepted: bool = True
    coverage: float = 1.0
    warnings: tuple[str, ...] = ()
    total_iterations: int = 0  # LM iterations of every stage of every pass (the rerun ``iteration`` timeline)
    verdicts: tuple = ()  # per view `lfgraph.refinement.assess.ViewVerdict`
    heldout_before_px: float = float("nan")  # held-out tracks' RMS with the input calibration
    heldout_after_px: float = float("nan")  # ... and with refits that did not see them
    sigma_px: float = float("nan")  # the measurement sigma the posterior uses (px per coordinate)
    frames_dropped: tuple[int, ...] = ()  # frames whose tracks were mostly mismatches
    # CPU seconds of matching + filters (the process's CPU less the adjustment's) and of the adjustment; seconds_* are
    # wall time, and as a frame's tracking runs in a worker thread while the frames before it are refitted,
    # seconds_matching + seconds_adjustment can exceed seconds
    cpu_seconds_matching: float = 0.0
    cpu_seconds_adjustment: float = 0.0

    def verdict_counts(self) -> dict[str, int]:
        """Views per verdict: every verdict, zero counts included, always in the order OK, DRIFTED, UNCERTAIN,
        REFERENCE (a study's CSV keeps its columns from seed to seed)."""
        out = dict.fromkeys(VERDICTS, 0)
        for v in self.verdicts:
            out[v.verdict] = out.get(v.verdict, 0) + 1
        return out

    def metrics(self) -> dict:
        """``{"refinement": ...}`` as stored in ``Calibration.metrics`` (JSON-ready: frames used and why it stopped,
        tracks per filter and frame, the stages, the verdicts, the RMS before/after and on held-out tracks)."""
        return {
            "refinement": {
                "frames_used": self.frames_used, "stop_reason": self.stop_reason, "accepted": self.accepted,
                "coverage": self.coverage, "warnings": list(self.warnings),
                "total_iterations": self.total_iterations,
                "rms_before_px": self.rms_before_px, "rms_after_px": self.rms_after_px,
                "heldout_before_px": _num(self.heldout_before_px), "heldout_after_px": _num(self.heldout_after_px),
                "sigma_px": _num(self.sigma_px), "frames_dropped": list(self.frames_dropped),
                "verdicts": [v.as_dict() for v in self.verdicts],
                "frame_counts": list(self.frame_counts),
                "stages": [{"name": str(s.name), "landmarks": s.landmarks, "rms_before_px": s.rms_before_px,
                            "rms_after_px": s.rms_after_px, "iterations": s.iterations,
                            "max_rotation_change_deg": float(np.max(s.rotation_change_deg)),
                            "max_position_change_mm": float(np.max(s.position_change_mm))}
                           for s in self.stages],
            }
        }


def _num(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None
