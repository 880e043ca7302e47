"""What a lens model is to lfgraph: `LensModel`, one instance per model module (`radtan`, `fisheye`, `unified`),
registered in `lfgraph.lenses`. Everything that differs between models is here or in the model's module: its
coefficients (as ``calibration.json`` stores them and in GTSAM's tangent order), its GTSAM calibration class (and so
every GTSAM factor of it: ``PriorFactor``, ``GenericProjectionFactor``, ``GeneralSFMFactor2``, ...), its distortion,
Jacobian and inverse, where it folds, its OpenCV form and which of its coefficients are tangential."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from lfgraph.core.camera import Intrinsics

UNDISTORT_MAX_ITERATIONS = 50
UNDISTORT_TOLERANCE = 1e-15  # normalised units; ~1e-12 px at f = 1000 px
UNDISTORT_RESIDUAL_LIMIT = 1e-11  # normalised units; larger residuals mean the pixel has no inverse
# every coefficient an `Intrinsics` holds (a model uses some of them; the others must be 0)
COEFFICIENTS = ("k1", "k2", "p1", "p2", "k3", "k4", "xi")
HEAD = ("fx", "fy", "s", "cx", "cy")  # every GTSAM calibration's tangent starts so (s: the skew, always 0 here)

# (x, y, k1, k2, p1, p2, k3, k4, xi, jacobian) -> (xd, yd) or (xd, yd, dxd/dx, dxd/dy, dyd/dx, dyd/dy)
BulkMap = Callable[..., tuple[np.ndarray, ...]]
# (x, y, k1, k2, p1, p2, k3, k4, xi) -> (*x.shape, 2, len(tangent)): d (xd, yd) / d each coefficient, tangent order
CoefficientJacobian = Callable[..., np.ndarray]


@dataclass(frozen=True)
class LensModel:
    """One lens model.

    Attributes:
        name: as ``Intrinsics.lens`` and ``calibration.json`` name it.
        gtsam_name: GTSAM's calibration class (``Cal3DS2``); its factors are named after it.
        coefficients: the model's coefficients in ``calibration.json``'s order (a subset of `COEFFICIENTS`).
        tangent: the model's coefficients in GTSAM's tangent order (after `HEAD`).
        bulk_map: the distortion of normalised coordinates with its Jacobian, every coefficient an array.
        undistort: (V, N, 2) distorted normalised coordinates and the V views' `Intrinsics` -> (V, N, 2) undistorted
            ones, NaN where the model has no inverse.
        folded: (intrinsics, rays (N, 3), xy (N, 2) = rays' normalised coordinates, px (N, 2) = their projection) ->
            (N,) True where the projection lies beyond the model's fold (plausible but wrong).
        tangential: the coefficients held at 0 unless tangential distortion is asked for.
        wide: its field of view may end inside the image (rectification crops, the wide-board pass, the bounds of
            a wide field of view).
        opencv: ``"pinhole"`` (``cv2``, distortion k1 k2 p1 p2 k3=0), ``"fisheye"`` (``cv2.fisheye``, k1..k4) or None.
        check: an `Intrinsics` -> a problem (text) or None, beyond the common checks.
        off_axis_deg: (r, xi) -> the angle (deg) from the axis of the ray the model without distortion images at a
            normalised radius r (NaN beyond its image): a nominal field of view.
        coefficient_jacobian: the distortion's derivatives by its coefficients (in ``tangent`` order), for the
            bulk calibration solver (`lfgraph.engine.board_problem`); None: calibrations of it take GTSAM's factors.
    """

    name: str
    gtsam_name: str
    coefficients: tuple[str, ...]
    tangent: tuple[str, ...]
    bulk_map: BulkMap
    undistort: Callable[[np.ndarray, Sequence[Intrinsics]], np.ndarray]
    folded: Callable[[Intrinsics, np.ndarray, np.ndarray, np.ndarray], np.ndarray]
    tangential: tuple[str, ...] = ()
    wide: bool = False
    opencv: str | None = None
    check: Callable[[Intrinsics], str | None] | None = None
    off_axis_deg: Callable[[float, float], float] = lambda r, xi: float(np.degrees(np.arctan(r)))
    coefficient_jacobian: CoefficientJacobian | None = None

    @property
    def tangent_size(self) -> int:
        """The size of the model's GTSAM calibration tangent (9 for Cal3DS2 and Cal3Fisheye, 10 for Cal3Unified)."""
        return len(HEAD) + len(self.tangent)

    def free_size(self, tangential: bool) -> int:
        """How many of a view's intrinsics a calibration estimates under this model: fx, fy, cx, cy and every
        coefficient, the tangential ones only when asked for (skew is never free)."""
        return 4 + len(self.coefficients) - (0 if tangential else len(self.tangential))

    def gtsam(self, prefix: str = "", module: Any = None) -> Any:
        """GTSAM's class ``prefix + gtsam_name`` (``"PriorFactor"`` -> ``PriorFactorCal3DS2``) from ``module``
        (``gtsam`` by default; ``gtsam_unstable`` for the board factors), or None where GTSAM has none."""
        if module is None:
            import gtsam as module
        return getattr(module, prefix + self.gtsam_name, None)

    def vector(self, intr: Intrinsics) -> list[float]:
        """The calibration in GTSAM's tangent order (skew 0): what its constructor and ``vector()`` take."""
        return [intr.fx, intr.fy, 0.0, intr.cx, intr.cy, *(getattr(intr, k) for k in self.tangent)]

    def to_gtsam(self, intr: Intrinsics) -> Any:
        """The GTSAM calibration of ``intr`` (skew 0)."""
        return self.gtsam()(*self.vector(intr))

    def from_gtsam(self, cal: Any) -> dict[str, float]:
        """fx, fy, cx, cy and the coefficients by name from the model's GTSAM calibration (the skew dropped; its
        accessors are named as the coefficients: ``k1()``, ``xi()``; its ``vector()`` is not the whole tangent for
        every class)."""
        return {"fx": cal.fx(), "fy": cal.fy(), "cx": cal.px(), "cy": cal.py(),
                **{k: float(getattr(cal, k)()) for k in self.tangent}}

    def distort(self, intr: Intrinsics, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The model's distortion of normalised coordinates with ``intr``'s coefficients."""
        return self.bulk_map(x, y, *(getattr(intr, k) for k in COEFFICIENTS), jacobian=False)

    def opencv_distortion(self, intr: Intrinsics) -> np.ndarray:
        """OpenCV's distortion vector of ``intr``; ValueError for a model OpenCV's main modules lack."""
        if self.opencv == "fisheye":
            return np.array([intr.k1, intr.k2, intr.k3, intr.k4])
        if self.opencv == "pinhole":
            return np.array([intr.k1, intr.k2, intr.p1, intr.p2, 0.0])
        raise ValueError(f"a {self.name} lens has no OpenCV distortion vector (OpenCV's main modules have no such "
                         "model); use Intrinsics.undistort / project")

    def from_opencv_distortion(self, d: np.ndarray) -> dict[str, float]:
        """The coefficients of OpenCV's distortion vector ``d`` for this model: ``cv2.fisheye``'s four k1..k4, or
        ``cv2``'s k1 k2 p1 p2 (more coefficients must be 0: k3 and higher are not modelled); ValueError otherwise."""
        d = np.asarray(d, dtype=np.float64).ravel()
        if self.opencv == "fisheye":
            if d.size != 4:
                raise ValueError(f"a fisheye distortion has 4 coefficients (k1 k2 k3 k4), got {d.size}")
            return dict(zip(("k1", "k2", "k3", "k4"), d.tolist(), strict=True))
        if self.opencv != "pinhole":
            raise ValueError(f"OpenCV has no {self.name} lens in its main modules; choose a pinhole or fisheye model")
        if d.size < 4:
            raise ValueError(f"distortion needs at least 4 coefficients (k1 k2 p1 p2), got {d.size}")
        if np.any(np.abs(d[4:]) > 0):
            raise ValueError(f"distortion coefficients beyond k1 k2 p1 p2 must be 0 (k3 and higher are not modelled), "
                             f"got {d[4:].tolist()}")
        return dict(zip(("k1", "k2", "p1", "p2"), d[:4].tolist(), strict=True))
