"""Noise-model factories: the one place that knows GTSAM's tangent orders, and robust kernels by name.

GTSAM 4.3 pitfall: ``noiseModel.Diagonal.Sigmas`` with any sigma below 1e-8 silently becomes a ``Constrained`` model
and forces a QR solver (~100x slower). Every factory here clamps sigmas to ``MIN_SIGMA``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import gtsam
import numpy as np

from lfgraph.lenses import lens_model

MIN_SIGMA = 1e-7  # keep well above GTSAM's 1e-8 "constrained" threshold
FREE_SIGMA = 1e8  # "no information" sigma for what the data determine (a pull of 1e-16 per unit²)
HELD_SIGMA = 1e-6  # tight prior for what a stage holds (px, -, rad, m); >= 1e-8 keeps GTSAM's fast solver
GAUGE_SIGMA = 1e-8  # rad and m: the reference view's pose is the identity by definition (Isotropic stays fast)

# Cal3DS2 tangent order (its vector()): fx, fy, s, u0, v0, k1, k2, p1, p2
CAL3DS2_FIELDS = ("fx", "fy", "s", "cx", "cy", "k1", "k2", "p1", "p2")

# name -> (GTSAM M-estimator from a threshold in whitened units, the usual threshold in measurement sigmas)
_KERNELS: dict[str, tuple[Callable[[float], gtsam.noiseModel.mEstimator.Base], float]] = {}
DEFAULT_THRESHOLDS: dict[str, float] = {}  # the usual thresholds by name (as registered)


def register_kernel(name: str, create: Callable[[float], gtsam.noiseModel.mEstimator.Base], usual: float) -> None:
    """Make a robust kernel known by ``name`` (a new name, lower case) to `RobustKernel` and every ``--robust``:
    ``create(threshold)`` builds GTSAM's M-estimator for a threshold in whitened units (measurement sigmas), and
    ``usual`` is the threshold a bare name takes."""
    if not isinstance(name, str) or name != name.strip().lower() or name in ("", "none") or name in _KERNELS:
        raise ValueError(f"a robust kernel needs a new lower-case name, got {name!r}")
    if not usual > 0:
        raise ValueError(f"robust kernel {name}: the usual threshold must be positive, got {usual!r}")
    _KERNELS[name] = (create, float(usual))
    DEFAULT_THRESHOLDS[name] = float(usual)


def kernel_names() -> tuple[str, ...]:
    """``none`` and every registered kernel's name."""
    return ("none", *_KERNELS)


# the usual tuning constants, in measurement sigmas: 95 % efficiency on Gaussian noise (GTSAM's default Cauchy is 0.1;
# Geman–McClure's and DCS's 1.0 had 44 % and 64 %: their constants here are computed from GTSAM's own weights in
# tests/engine/test_bulk_noise.py). A DCS threshold is a distance as every other: GTSAM's parameter is its square.
_M = gtsam.noiseModel.mEstimator
for _name, _create, _usual in (("huber", _M.Huber.Create, 1.345), ("cauchy", _M.Cauchy.Create, 2.385),  # one line each
                               ("tukey", _M.Tukey.Create, 4.685), ("gm", _M.GemanMcClure.Create, 3.787),
                               ("gemanmcclure", _M.GemanMcClure.Create, 3.787),
                               ("dcs", lambda t: _M.DCS.Create(t * t), 1.898),
                               ("welsch", _M.Welsch.Create, 2.985), ("fair", _M.Fair.Create, 1.3998)):
    register_kernel(_name, _create, _usual)
KERNEL_UNITS = ("px", "sigma")
KERNEL_NAMES = kernel_names()  # the built-in ones (`kernel_names` also sees later registrations)
# thresholds outside this make every residual an outlier or none (GTSAM's solve then becomes indeterminate)
KERNEL_THRESHOLD_RANGE = (1e-3, 1e3)


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


def gauge_pose_noise() -> gtsam.noiseModel.Base:
    """The reference view's pose prior: the identity by definition (an Isotropic model stays on the fast solver)."""
    return gtsam.noiseModel.Isotropic.Sigma(6, GAUGE_SIGMA)


def range_noise(sigma_m: float) -> gtsam.noiseModel.Base:
    """1-D range noise in metres."""
    return gtsam.noiseModel.Isotropic.Sigma(1, float(_sigmas([sigma_m])[0]))


def calibration_noise(sigmas: Sequence[float]) -> gtsam.noiseModel.Base:
    """Diagonal prior noise of a calibration of any lens model from its sigmas in GTSAM's tangent order (9 for
    Cal3DS2 and Cal3Fisheye, 10 for Cal3Unified: `lens_noise`), each floored at `MIN_SIGMA`."""
    return gtsam.noiseModel.Diagonal.Sigmas(_sigmas(sigmas))


def lens_noise(lens: str, focal_px: float, principal_px: float, distortion: float,
               tangential: float = MIN_SIGMA, skew_px: float = MIN_SIGMA, xi: float | None = None
               ) -> gtsam.noiseModel.Base:
    """Prior noise of one lens model in its GTSAM tangent order: ``radtan`` (Cal3DS2: fx fy s cx cy k1 k2 p1 p2),
    ``fisheye`` (Cal3Fisheye: fx fy s cx cy k1 k2 k3 k4) or ``unified`` (Cal3Unified: fx fy s cx cy k1 k2 p1 p2 xi).

    Args:
        focal_px, principal_px: sigma of fx and fy, of cx and cy (pixels).
        distortion: sigma of the radial coefficients (k1, k2; k1..k4 for fisheye) and of xi.
        tangential: sigma of p1, p2 (radtan and unified); the default holds them at their prior.
        skew_px: sigma of the skew; the default holds it at 0 (the models have none).
        xi: sigma of the unified model's xi; None: ``distortion``.
    """
    model = lens_model(lens)
    head = [focal_px, focal_px, skew_px, principal_px, principal_px]
    tail = [tangential if k in model.tangential else distortion if k != "xi" or xi is None else xi
            for k in model.tangent]
    return gtsam.noiseModel.Diagonal.Sigmas(_sigmas(head + tail))


@dataclass(frozen=True)
class RobustKernel:
    """An M-estimator by name with its threshold: in pixels (``unit="px"``, the default for a number you give) or in
    measurement sigmas (``unit="sigma"``).

    ``RobustKernel.parse("huber:0.5")`` is Huber at 0.5 px; ``"huber:1.345sigma"`` at 1.345 measurement sigmas;
    ``RobustKernel("cauchy")`` (no number) takes the kernel's usual tuning constant, in sigmas (Huber 1.345, Cauchy
    2.385, Tukey 4.685, Welsch 2.985, Fair 1.3998, Geman–McClure 3.787, DCS 1.898: 95 % efficiency on Gaussian
    noise; a DCS threshold is the distance where its weight starts to fall, GTSAM's parameter its square);
    ``RobustKernel("none")`` is plain least squares. A pixel threshold is turned into sigmas by the measurement sigma
    of the fit that uses it (`estimator`): `refine` estimates that sigma from the data (~0.05 px on clean scenes),
    `calibrate` uses ``corner_sigma_px``. Studies swap kernels by building these (or by name).
    """

    name: str = "none"
    threshold: float | None = None
    unit: str = "px"

    def __post_init__(self) -> None:
        if not isinstance(self.name, str):
            raise TypeError(f"RobustKernel name must be a string such as 'huber', got {type(self.name).__name__}")
        name = self.name.strip().lower()
        if name not in kernel_names():
            raise ValueError(f"unknown robust kernel {self.name!r}; choose from {', '.join(kernel_names())} "
                             f"(optionally NAME:THRESHOLD in px, or NAME:THRESHOLDsigma, e.g. huber:0.5)")
        if self.unit not in KERNEL_UNITS:
            raise ValueError(f"RobustKernel unit must be one of {', '.join(KERNEL_UNITS)}, got {self.unit!r}")
        object.__setattr__(self, "name", name)
        if name == "none":
            object.__setattr__(self, "threshold", None)
            return
        if self.threshold is None:  # the usual constant, which is defined in sigmas
            object.__setattr__(self, "threshold", DEFAULT_THRESHOLDS[name])
            object.__setattr__(self, "unit", "sigma")
            return
        threshold = self.threshold
        if not (isinstance(threshold, int | float) and not isinstance(threshold, bool)
                and KERNEL_THRESHOLD_RANGE[0] <= threshold <= KERNEL_THRESHOLD_RANGE[1]):
            raise ValueError(f"robust kernel threshold must be a number from {KERNEL_THRESHOLD_RANGE[0]:g} to "
                             f"{KERNEL_THRESHOLD_RANGE[1]:g} ({self.unit}), got {threshold!r} for {name}")
        object.__setattr__(self, "threshold", float(threshold))

    @classmethod
    def parse(cls, spec: str | None) -> RobustKernel:
        """``"huber:0.5"`` (px), ``"huber:1.345sigma"`` (measurement sigmas), ``"cauchy"`` (its usual constant, in
        sigmas), ``"none"``/``""``/None.

        Raises:
            ValueError: unknown kernel name or a threshold that is not a positive number.
        """
        if spec is not None and not isinstance(spec, str):
            raise TypeError(f"a robust kernel spec is a string such as 'huber:0.5', got {type(spec).__name__}")
        if spec is None or spec.strip().lower() in ("", "none"):
            return cls("none")
        name, _, value = spec.strip().partition(":")
        if not value:
            return cls(name)
        text, unit = value.strip().lower(), "px"
        for suffix, u in (("sigmas", "sigma"), ("sigma", "sigma"), ("px", "px")):
            if text.endswith(suffix):
                text, unit = text[: -len(suffix)].strip(), u
                break
        try:
            threshold = float(text)
        except ValueError:
            raise ValueError(f"robust kernel threshold must be a number (px, or with 'sigma'), got {value!r} in "
                             f"{spec!r}") from None
        return cls(name, threshold, unit)

    def sigmas(self, sigma_px: float) -> float | None:
        """The threshold in measurement sigmas for a measurement sigma of ``sigma_px`` (None for ``none``)."""
        if self.threshold is None:
            return None
        return self.threshold if self.unit == "sigma" else self.threshold / float(_sigmas([sigma_px])[0])

    def estimator(self, sigma_px: float = 1.0) -> gtsam.noiseModel.mEstimator.Base | None:
        """GTSAM's M-estimator for whitened residuals of a ``sigma_px`` measurement noise (None for ``none``)."""
        if self.name == "none":
            return None
        threshold = self.sigmas(sigma_px)
        return _KERNELS[self.name][0](threshold)

    def __str__(self) -> str:
        if self.threshold is None:
            return self.name
        return f"{self.name}:{self.threshold:g}" + ("sigma" if self.unit == "sigma" else "")


# What a user may pass wherever a measurement noise is asked for: a kernel name ("cauchy:0.5"), a RobustKernel, a
# GTSAM M-estimator (wrapped around the isotropic pixel noise of the configured sigma) or a full GTSAM noise model
# (used as it is; the sigma setting is then ignored).
NoiseSpec = str | RobustKernel | gtsam.noiseModel.mEstimator.Base | gtsam.noiseModel.Base | None
Noise = RobustKernel | gtsam.noiseModel.mEstimator.Base | gtsam.noiseModel.Base


def as_noise(spec: NoiseSpec) -> Noise:
    """Normalise a `NoiseSpec` once, at the edge (strings are parsed here and nowhere else).

    Raises:
        ValueError: a bad kernel string; TypeError: an object that is none of the accepted kinds.
    """
    if spec is None or isinstance(spec, str):
        return RobustKernel.parse(spec)
    if isinstance(spec, RobustKernel | gtsam.noiseModel.mEstimator.Base | gtsam.noiseModel.Base):
        return spec
    raise TypeError(f"a noise model must be a kernel name such as 'cauchy:0.5', a RobustKernel, a "
                    f"gtsam.noiseModel.mEstimator object or a gtsam noise model; got {type(spec).__name__}")


def describe_noise(noise: Noise) -> str:
    """Short text for logs and reports."""
    if isinstance(noise, RobustKernel):
        return str(noise)
    return type(noise).__name__


def measurement_noise(noise: Noise, sigma_px: float, dim: int = 2) -> gtsam.noiseModel.Base:
    """The noise model of one image measurement: isotropic ``sigma_px`` wrapped in the kernel, or the user's model.

    Raises:
        ValueError: a full GTSAM model of the wrong dimension.
    """
    if isinstance(noise, gtsam.noiseModel.Base):
        if noise.dim() != dim:
            raise ValueError(f"the measurement noise model must have dimension {dim}, got {noise.dim()}")
        return noise
    base = gtsam.noiseModel.Isotropic.Sigma(dim, float(_sigmas([sigma_px])[0]))
    estimator = noise if isinstance(noise, gtsam.noiseModel.mEstimator.Base) else noise.estimator(sigma_px)
    return base if estimator is None else gtsam.noiseModel.Robust.Create(estimator, base)
