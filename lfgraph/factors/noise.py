"""Noise-model factories: the one place that knows GTSAM's tangent orders, and robust kernels by name.

GTSAM 4.3 pitfall: ``noiseModel.Diagonal.Sigmas`` with any sigma below 1e-8 silently becomes a ``Constrained`` model
and forces a QR solver (~100x slower). Every factory here clamps sigmas to ``MIN_SIGMA``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import gtsam
import numpy as np

MIN_SIGMA = 1e-7  # keep well above GTSAM's 1e-8 "constrained" threshold

# Cal3DS2 tangent order (its vector()): fx, fy, s, u0, v0, k1, k2, p1, p2
CAL3DS2_FIELDS = ("fx", "fy", "s", "cx", "cy", "k1", "k2", "p1", "p2")

_KERNELS: dict[str, Callable[[float], object]] = {
    "huber": gtsam.noiseModel.mEstimator.Huber.Create,
    "cauchy": gtsam.noiseModel.mEstimator.Cauchy.Create,
    "tukey": gtsam.noiseModel.mEstimator.Tukey.Create,
    "gm": gtsam.noiseModel.mEstimator.GemanMcClure.Create,
    "gemanmcclure": gtsam.noiseModel.mEstimator.GemanMcClure.Create,
    "dcs": gtsam.noiseModel.mEstimator.DCS.Create,
    "welsch": gtsam.noiseModel.mEstimator.Welsch.Create,
    "fair": gtsam.noiseModel.mEstimator.Fair.Create,
}
DEFAULT_THRESHOLDS = {"huber": 1.345, "cauchy": 0.1, "tukey": 4.685, "gm": 1.0, "gemanmcclure": 1.0, "dcs": 1.0,
                      "welsch": 2.985, "fair": 1.3998}
KERNEL_NAMES = ("none", *_KERNELS)


def _sigmas(values: Sequence[float]) -> np.ndarray:
    s = np.asarray(values, dtype=np.float64)
    if not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise ValueError(f"sigmas must be positive and finite, got {s.tolist()}")
    return np.maximum(s, MIN_SIGMA)


def pixel_noise(sigma_px: float) -> gtsam.noiseModel.Base:
    """Isotropic 2-D measurement noise, ``sigma_px`` pixels per coordinate."""
    return gtsam.noiseModel.Isotropic.Sigma(2, float(_sigmas([sigma_px])[0]))


def point_noise(sigma_m: float) -> gtsam.noiseModel.Base:
    """Isotropic 3-D point noise in metres."""
    return gtsam.noiseModel.Isotropic.Sigma(3, float(_sigmas([sigma_m])[0]))


def pose_noise(rot_sigma_rad: float | Sequence[float], trans_sigma_m: float | Sequence[float]) -> gtsam.noiseModel.Base:
    """Pose3 prior noise; GTSAM's Pose3 tangent is rotation first, then translation."""
    rot = np.broadcast_to(np.asarray(rot_sigma_rad, dtype=np.float64), (3,))
    trans = np.broadcast_to(np.asarray(trans_sigma_m, dtype=np.float64), (3,))
    return gtsam.noiseModel.Diagonal.Sigmas(_sigmas(np.concatenate([rot, trans])))


def calibration_noise(focal_px: float, principal_px: float, radial: float | Sequence[float],
                      tangential: float = MIN_SIGMA, skew_px: float = MIN_SIGMA) -> gtsam.noiseModel.Base:
    """Cal3DS2 prior noise in its tangent order (fx, fy, s, u0, v0, k1, k2, p1, p2).

    Args:
        focal_px: sigma of fx and fy (pixels).
        principal_px: sigma of cx and cy (pixels).
        radial: sigma of k1 and k2 (one value or two).
        tangential: sigma of p1, p2; the default holds them at their prior (0).
        skew_px: sigma of the skew; the default holds it at 0 (the model has none).
    """
    k = np.broadcast_to(np.asarray(radial, dtype=np.float64), (2,))
    return gtsam.noiseModel.Diagonal.Sigmas(
        _sigmas([focal_px, focal_px, skew_px, principal_px, principal_px, k[0], k[1], tangential, tangential]))


def parse_robust(spec: str | None) -> tuple[str, float | None]:
    """``"huber:1.345"`` -> ("huber", 1.345); ``"cauchy"`` -> ("cauchy", default); ``"none"``/None -> ("none", None).

    Raises:
        ValueError: unknown kernel name or a threshold that is not a positive number.
    """
    if spec is None or spec.strip().lower() in ("", "none"):
        return "none", None
    name, _, value = spec.strip().lower().partition(":")
    if name not in _KERNELS:
        raise ValueError(f"unknown robust kernel {name!r}; choose from {', '.join(KERNEL_NAMES)} "
                         f"(optionally NAME:THRESHOLD, e.g. huber:1.345)")
    if not value:
        return name, DEFAULT_THRESHOLDS[name]
    try:
        threshold = float(value)
    except ValueError:
        raise ValueError(f"robust kernel threshold must be a number, got {value!r} in {spec!r}") from None
    if not (np.isfinite(threshold) and threshold > 0):
        raise ValueError(f"robust kernel threshold must be positive, got {threshold} in {spec!r}")
    return name, threshold


def robust(base: gtsam.noiseModel.Base, kernel: str = "huber", threshold: float | None = None) -> gtsam.noiseModel.Base:
    """Wrap ``base`` in an M-estimator chosen by name (``none`` returns ``base``). Threshold is in sigmas."""
    name, default = parse_robust(kernel if threshold is None else f"{kernel}:{threshold}")
    if name == "none":
        return base
    return gtsam.noiseModel.Robust.Create(_KERNELS[name](default), base)
