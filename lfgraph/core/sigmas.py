"""The one record of how sure lfgraph is of each view: `Sigmas`, 1-sigma per view of its pose and intrinsics, in the
view's own frame.

Inside, SI units and GTSAM's order: a pose's six in Pose3's tangent (rotation about the view's x, y, z axes in
radians, then position along them in metres: the body frame, where a Pose3 perturbation ``T * Exp(xi)`` lives),
fx, fy, cx, cy in pixels, distortion coefficients by name. At the edges, named units: ``calibration.json`` stores per
view ``fx_px``, ``fy_px``, ``cx_px``, ``cy_px``, the coefficients (``k1``, ``k2``, ``xi``), ``rotation_deg`` and
``position_mm`` (3 each) — `to_metrics` is the one writer, `from_metrics` the one reader (also of calibrate-scene's
older ``{"views": [...]}``). `from_marginals` is the one reader of a posterior (calibrate, calibrate-scene); the
design tolerances of a self-calibration and a refinement's drift model are built with `uniform`, and a refinement's
priors are a drift `combined` with the input's own sigmas.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lfgraph.lenses import COEFFICIENTS, HEAD, lens_model

POSE_SIZE = 6  # rotation x, y, z (rad), position x, y, z (m)
INTRINSIC_NAMES = ("fx_px", "fy_px", "cx_px", "cy_px")
_INTRINSIC_TANGENT = tuple(HEAD.index(k) for k in ("fx", "fy", "cx", "cy"))  # their places in a calibration's tangent


@dataclass(frozen=True, eq=False)
class Sigmas:
    """Per-view 1-sigma.

    Attributes:
        pose: (V, 6) rotation about the view's x, y, z axes (rad), then position along them (m).
        intrinsics: (V, 4) fx, fy, cx, cy (px).
        distortion: coefficient name -> (V,) sigma (NaN for a view whose model has no such coefficient).
    """

    pose: np.ndarray
    intrinsics: np.ndarray
    distortion: Mapping[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        pose = np.asarray(self.pose, dtype=np.float64)
        intr = np.asarray(self.intrinsics, dtype=np.float64)
        if pose.ndim != 2 or pose.shape[1] != POSE_SIZE or intr.shape != (len(pose), len(INTRINSIC_NAMES)):
            raise ValueError(f"Sigmas: pose must be (V, 6) and intrinsics (V, 4), got {pose.shape} and {intr.shape}")
        dist = {str(k): np.broadcast_to(np.asarray(v, dtype=np.float64), (len(pose),)).copy()
                for k, v in self.distortion.items()}
        object.__setattr__(self, "pose", pose)
        object.__setattr__(self, "intrinsics", intr)
        object.__setattr__(self, "distortion", dist)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Sigmas) and np.array_equal(self.pose, other.pose) and np.array_equal(
            self.intrinsics, other.intrinsics) and self.distortion.keys() == other.distortion.keys() and all(
            np.array_equal(v, other.distortion[k], equal_nan=True) for k, v in self.distortion.items())

    __hash__ = None  # mutable arrays inside

    @property
    def num_views(self) -> int:
        """The number of views."""
        return len(self.pose)

    @property
    def rotation_deg(self) -> np.ndarray:
        """(V, 3) about the view's x, y, z axes, degrees."""
        return np.degrees(self.pose[:, :3])

    @property
    def position_mm(self) -> np.ndarray:
        """(V, 3) along the view's x, y, z axes, millimetres."""
        return 1e3 * self.pose[:, 3:]

    @classmethod
    def uniform(cls, num_views: int, rotation_rad: float | Sequence[float], position_m: float | Sequence[float],
                focal_px: float, principal_px: float, distortion: Mapping[str, float] | None = None) -> Sigmas:
        """The same sigmas for every view (design tolerances, a drift model): a rotation sigma per axis (x, y, z)
        or one for all, likewise the position."""
        pose = np.concatenate([np.broadcast_to(np.asarray(rotation_rad, dtype=np.float64), (3,)),
                               np.broadcast_to(np.asarray(position_m, dtype=np.float64), (3,))])
        return cls(np.tile(pose, (num_views, 1)), np.tile([focal_px, focal_px, principal_px, principal_px],
                                                          (num_views, 1)),
                   {k: np.full(num_views, float(v)) for k, v in (distortion or {}).items()})

    def combined(self, other: Sigmas) -> Sigmas:
        """Root sum of squares with ``other`` (independent uncertainties: a drift and the input's own); a
        coefficient only one of them holds keeps its sigma."""
        none = np.full(self.num_views, np.nan)
        pairs = {k: np.stack([self.distortion.get(k, none), other.distortion.get(k, none)])
                 for k in dict.fromkeys([*self.distortion, *other.distortion])}
        dist = {k: np.where(np.isnan(p).all(axis=0), np.nan, np.sqrt(np.nansum(p**2, axis=0)))
                for k, p in pairs.items()}
        return Sigmas(np.hypot(self.pose, other.pose), np.hypot(self.intrinsics, other.intrinsics), dist)

    def view(self, v: int) -> dict[str, Any]:
        """View ``v`` in ``calibration.json``'s named units: fx_px, fy_px, cx_px, cy_px, its coefficients,
        rotation_deg and position_mm (3 each)."""
        return {**{k: float(x) for k, x in zip(INTRINSIC_NAMES, self.intrinsics[v], strict=True)},
                **{k: float(s[v]) for k, s in self.distortion.items() if np.isfinite(s[v])},
                "rotation_deg": [float(x) for x in self.rotation_deg[v]],
                "position_mm": [float(x) for x in self.position_mm[v]]}

    def to_metrics(self) -> list[dict[str, Any]]:
        """What ``calibration.json`` stores under ``metrics["sigmas"]``: one `view` per view."""
        return [self.view(v) for v in range(self.num_views)]

    @classmethod
    def from_metrics(cls, stored: object, num_views: int) -> Sigmas | None:
        """The sigmas a file stores (`to_metrics`, or calibrate-scene's older ``{"views": [...]}``), or None where
        absent, of another length, incomplete or not finite."""
        stored = stored.get("views") if isinstance(stored, Mapping) else stored
        if not isinstance(stored, list | tuple) or len(stored) != num_views or num_views == 0:
            return None
        try:
            intr = np.array([[float(s[k]) for k in INTRINSIC_NAMES] for s in stored])
            rot = np.array([[float(x) for x in s["rotation_deg"]] for s in stored])
            pos = np.array([[float(x) for x in s["position_mm"]] for s in stored])
            names = [k for k in COEFFICIENTS if any(k in s for s in stored)]  # other keys are not ours: ignored
            dist = {k: np.array([float(s.get(k, np.nan)) for s in stored]) for k in names}
        except (KeyError, TypeError, ValueError, AttributeError):
            return None
        if rot.shape != (num_views, 3) or pos.shape != (num_views, 3) or not (
                np.all(np.isfinite(intr)) and np.all(np.isfinite(rot)) and np.all(np.isfinite(pos))):
            return None
        return cls(np.concatenate([np.radians(rot), 1e-3 * pos], axis=1), intr, dist)

    def with_calibration_cov(self, joint: np.ndarray, lenses: Sequence[str]) -> Sigmas:
        """These sigmas with every view's intrinsics and coefficients read from ``joint``, the (DV, DV) covariance of
        every view's calibration (views in order, each in its ``lenses`` model's tangent order, as `from_marginals`
        reads them; e.g. calibrate-scene's, its weak modes widened to the tracks' own scatter); poses keep theirs.

        Raises:
            ValueError: ``joint`` is not the size the lenses give.
        """
        dims = [lens_model(lens).tangent_size for lens in lenses]
        ends = np.cumsum(dims)
        if len(lenses) != self.num_views or np.shape(joint) != (ends[-1], ends[-1]):
            raise ValueError(f"Sigmas.with_calibration_cov: a {np.shape(joint)} covariance for {self.num_views} views "
                             f"of {sum(dims)} calibration parameters")
        n = self.num_views
        blocks = {v: joint[e - d:e, e - d:e] for v, (d, e) in enumerate(zip(dims, ends, strict=True))}
        blocks |= {n + v: np.diag(self.pose[v] ** 2) for v in range(n)}
        return Sigmas.from_marginals(_Blocks(blocks), range(n), range(n, 2 * n), lenses)

    @classmethod
    def from_marginals(cls, marginals: Any, calib_keys: Sequence[int], pose_keys: Sequence[int],
                       lenses: Sequence[str], scale: float = 1.0, tangential: bool = False) -> Sigmas:
        """The marginal sigmas of each view's calibration and pose (``marginals.block(key)``: covariance in GTSAM's
        tangent order; a pose's in its body frame, so about / along the view's own axes), times ``scale`` (e.g. the
        a-posteriori noise factor); the coefficients each view's model estimates (its tangential ones only with
        ``tangential``: held at 0 otherwise, a sigma of nothing)."""
        n = len(calib_keys)
        pose, intr = np.zeros((n, POSE_SIZE)), np.zeros((n, len(INTRINSIC_NAMES)))
        dist: dict[str, np.ndarray] = {}
        for v, (ck, pk) in enumerate(zip(calib_keys, pose_keys, strict=True)):
            kc = np.sqrt(np.maximum(np.diag(marginals.block(ck)), 0.0)) * scale
            pose[v] = np.sqrt(np.maximum(np.diag(marginals.block(pk)), 0.0)) * scale
            intr[v] = kc[list(_INTRINSIC_TANGENT)]
            model = lens_model(lenses[v])
            for i, name in enumerate(model.tangent):
                if tangential or name not in model.tangential:
                    dist.setdefault(name, np.full(n, np.nan))[v] = kc[len(HEAD) + i]
        return cls(pose, intr, dist)


@dataclass(frozen=True)
class _Blocks:
    """Covariance blocks by key, read as `Sigmas.from_marginals` reads a marginals object."""

    blocks: Mapping[int, np.ndarray]

    def block(self, key: int) -> np.ndarray:
        return self.blocks[key]
