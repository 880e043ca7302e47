"""What self-calibration reports: coverage, stages, measured noise, posterior sigmas, what the frames (and not the
design priors) determined, and an overall verdict."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lfgraph.core.grid import ViewGrid
from lfgraph.core.sigmas import Sigmas
from lfgraph.selfcal.tracks import Coverage, PooledTracks

PRIOR_LIMITED = 0.5  # a mode whose posterior sigma is over half its prior sigma was set by the design, not frames

GAUGES = (
    "pose: the reference view is the rig frame (identity pose)",
    "scale: from the design pitch (position priors at the nominal grid) - scene frames carry no scale",
    "hidden principal-point gauge: seen through distortion, with the principal points' design priors; common zoom: "
    "through pinhole (radtan) lenses seen only through the views' small rotations, so set largely by the design "
    "focal length (absolute focal length and metric depth), through wide lenses (fisheye, unified at its held xi) seen "
    "by the lenses' angles; both modes' posterior sigmas are in 'modes'",
)


@dataclass(frozen=True)
class Mode:
    """A combination of every view's intrinsics that scene frames see weakly, with its posterior and prior sigma.

    Attributes:
        name: e.g. ``zoom``; unit: of the sigmas; effect: what an error in it does.
    """

    name: str
    unit: str
    posterior_sigma: float
    prior_sigma: float
    effect: str

    @property
    def ratio(self) -> float:
        """Posterior sigma over prior sigma (near 1: the frames added little to the design)."""
        return self.posterior_sigma / self.prior_sigma

    @property
    def from_prior(self) -> bool:
        """Whether the design prior, not the frames, set this mode (``ratio`` above `PRIOR_LIMITED`)."""
        return bool(self.ratio > PRIOR_LIMITED)

    def as_dict(self) -> dict:
        """The fields, ``ratio`` and ``from_prior`` as a JSON-ready dict."""
        return {"name": self.name, "unit": self.unit, "posterior_sigma": self.posterior_sigma,
                "prior_sigma": self.prior_sigma, "ratio": self.ratio, "from_prior": self.from_prior,
                "effect": self.effect}


def modes(joint_cov: np.ndarray, prior_sigmas: np.ndarray, grid: ViewGrid, distortion: bool) -> list[Mode]:
    """Posterior and prior sigma of the weakly seen modes.

    Args:
        joint_cov: (DV, DV) joint marginal covariance of every view's calibration (views in order; D its tangent
            size, the same for every view of a design: 9 for Cal3DS2 and Cal3Fisheye, 10 for Cal3Unified).
        prior_sigmas: (9,) the design tolerances in Cal3DS2 order (the groups' indices are every model's).
        distortion: whether k1, k2 were estimated.
    """
    n = grid.num_views
    off = np.array([grid.offset(v) for v in range(n)], dtype=float)  # (dr, dc)

    dim = len(joint_cov) // n

    def mode(weights: dict[int, np.ndarray]) -> tuple[float, float]:
        a = np.zeros(dim * n)
        for idx, w in weights.items():
            a[idx::dim] = w
        prior = float(np.sqrt(np.sum((a.reshape(n, dim)[:, :len(prior_sigmas)] * prior_sigmas) ** 2)))
        return float(np.sqrt(max(a @ joint_cov @ a, 0.0))), prior

    out = []
    mean = np.full(n, 1.0 / n)
    post, prior = mode({0: mean / 2, 1: mean / 2})
    out.append(Mode("zoom (mean focal length)", "px", post, prior,
                    "absolute focal length and metric depth; rectified alignment does not depend on it"))
    for idx, name in ((3, "cx"), (4, "cy")):
        post, prior = mode({idx: mean})
        out.append(Mode(f"common {name} shift", "px", post, prior, "where the rectified image centre lies"))
    for axis, idx, name, step in ((1, 3, "cx", "column"), (0, 4, "cy", "row")):
        d = off[:, axis] - off[:, axis].mean()
        if np.sum(d**2) == 0:
            continue
        post, prior = mode({idx: d / np.sum(d**2)})
        out.append(Mode(f"{name} per grid {step} (hidden principal-point gauge)", "px/step", post, prior,
                        "disparity at infinity: an error e moves infinity by e px per grid step"))
    if distortion:
        post, prior = mode({5: mean})
        out.append(Mode("mean k1", "-", post, prior, "straightness of lines far from the image centre"))
    return out


@dataclass(frozen=True)
class StageResult:
    """One stage: the parameter groups it freed, tracks, LM iterations and the reprojection RMS after it."""

    free: tuple[str, ...]
    tracks: int
    iterations: int
    rms_px: float

    def as_dict(self) -> dict:
        """The fields as a JSON-ready dict."""
        return {"free": list(self.free), "tracks": self.tracks, "iterations": self.iterations, "rms_px": self.rms_px}


@dataclass(frozen=True)
class SelfCalReport:
    """The result of `calibrate_scene` besides the calibration.

    Attributes:
        coverage: what the frames cover; stages: what ran; noise_px: tracking noise measured from the residuals
            (per coordinate); rms_px: final reprojection RMS; posterior: per-parameter sigmas; modes: the weakly
            seen combinations; distortion_estimated: False when tracks did not reach the corners (the stages held
            k2, or k1 and k2, at the design; the final stage's estimate rests largely on the design tolerances);
            warnings; seconds: wall time of tracking and of the graph; retracked: observations re-tracked with the
            calibrated local maps (`lfgraph.selfcal.retrack`); tracks: the tracks of the final fit; pins: what each
            pin did to the common zoom (`lfgraph.selfcal.pinned.PinResult`), empty without pins; scene: the scene's
            final fit without pins (`lfgraph.selfcal.pinned.SceneFit`: where `pin_scene` starts).
    """

    coverage: Coverage
    stages: tuple[StageResult, ...]
    noise_px: float
    rms_px: float
    posterior: Sigmas
    modes: tuple[Mode, ...]
    distortion_estimated: bool
    warnings: tuple[str, ...] = ()
    seconds: dict[str, float] = field(default_factory=dict)
    gauges: tuple[str, ...] = GAUGES
    retracked: int = 0
    tracks: PooledTracks | None = field(default=None, repr=False)
    pins: tuple = ()
    scene: object = field(default=None, repr=False)

    @property
    def zoom_from(self) -> str:
        """What set the common zoom (absolute focal length): the pins that fixed it, or the design focal length."""
        fixed = [p.name for p in self.pins if p.fixes_zoom]
        return ("pin " + ", ".join(fixed)) if fixed else "design focal length"

    @property
    def from_prior(self) -> list[Mode]:
        """The modes that the design priors rather than the frames determined (`Mode.from_prior`)."""
        return [m for m in self.modes if m.from_prior]

    @property
    def verdict(self) -> str:
        """``good``: the frames determined every mode; ``prior-limited``: some came from the design tolerances (the
        calibration is still usable for what does not depend on them); ``poor``: the fit is inconsistent."""
        if not np.isfinite(self.rms_px) or self.rms_px > 3.0 * max(self.noise_px, 1e-9):
            return "poor"
        return "prior-limited" if self.from_prior or not self.distortion_estimated else "good"

    def as_dict(self) -> dict:
        """The report as a JSON-ready dict (what ``--report-json`` writes), with the verdict and without the tracks."""
        return {"verdict": self.verdict, "scale_from": "design pitch", "gauges": list(self.gauges),
                "coverage": self.coverage.as_dict(), "stages": [s.as_dict() for s in self.stages],
                "noise_px": self.noise_px, "rms_px": self.rms_px, "distortion_estimated": self.distortion_estimated,
                "modes": [m.as_dict() for m in self.modes], "posterior_sigmas": {"views": self.posterior.to_metrics()},
                "warnings": list(self.warnings), "seconds": dict(self.seconds), "retracked": self.retracked,
                "zoom_from": self.zoom_from, "pins": [p.as_dict() for p in self.pins]}

    def text(self) -> str:
        """A readable summary for the CLI."""
        c = self.coverage
        lines = [f"frames {c.frames}, tracks {c.tracks}; depths {c.depth_m[0]:.3g}-{c.depth_m[2]:.3g} m (far/near "
                 f"{c.depth_ratio:.2f}); disparity per grid step {c.disparity_px[2]:.3g}-{c.disparity_px[0]:.3g} px",
                 "image regions missing: " + (", ".join(c.missing_regions()) or "none")
                 + f"; tracks reach {c.max_radius:.0%} of the half diagonal",
                 "stages:"]
        for s in self.stages:
            lines.append(f"  {'+'.join(s.free):<45} {s.tracks:>6} tracks {s.iterations:>3} it  rms {s.rms_px:.3f} px")
        lines.append(f"tracking noise {self.noise_px:.3f} px (from the residuals); final rms {self.rms_px:.3f} px"
                     + (f"; {self.retracked} observations re-tracked with the calibrated local maps"
                        if self.retracked else ""))
        post = self.posterior
        columns = {**dict(zip(("fx", "fy", "cx", "cy"), post.intrinsics.T, strict=True)),
                   **{k: post.distortion[k] for k in ("k1", "k2") if k in post.distortion}}
        lines.append("posterior 1-sigma, median (max) over views: " + ", ".join(
            f"{name} {np.nanmedian(c):.3g} ({np.nanmax(c):.3g})" for name, c in columns.items())
                     + f", rotation {np.median(self.posterior.rotation_deg):.2g} deg, position "
                       f"{np.median(self.posterior.position_mm):.2g} mm")
        lines.append("weakly seen modes (posterior / design prior sigma):")
        for m in self.modes:
            lines.append(f"  {m.name:<48} {m.posterior_sigma:.3g} / {m.prior_sigma:.3g} {m.unit}"
                         f"{'  <- from the design prior: ' + m.effect if m.from_prior else ''}")
        lines.extend(p.text() for p in self.pins)
        lines.append(f"common zoom (absolute focal length) from: {self.zoom_from}")
        lines.append("gauges: " + "; ".join(self.gauges))
        lines.extend(f"warning: {w}" for w in self.warnings)
        lines.append(f"verdict: {self.verdict}")
        return "\n".join(lines)
