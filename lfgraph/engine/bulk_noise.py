"""A GTSAM measurement noise model applied to many residuals at once: the bulk solvers' (`lfgraph.engine.schur`) way of
using any Gaussian model and any M-estimator without a GTSAM factor per observation.

GTSAM's semantics, which this reproduces (checked against GTSAM's own ``whiten`` and ``loss`` and against its
Levenberg–Marquardt on the same graph in tests/engine/test_bulk_noise.py):

- a Gaussian model whitens a residual ``r`` by its square-root information ``R`` (``e = R r``); the factor's error
  is ``0.5 |e|^2``;
- ``noiseModel.Robust(estimator, gaussian)`` then reweights the whitened residual and its Jacobian: with the
  ``Block`` scheme (GTSAM's default) both rows by ``sqrt(w(|e|))`` and the factor's error is ``loss(|e|)``; with
  ``Scalar`` each row by ``sqrt(w(e_i))`` and the error is ``loss(|e_0|) + loss(|e_1|)``.

The common estimators (Huber, Cauchy, Tukey, Geman–McClure, DCS, Welsch, Fair, Null) are evaluated by their
formulas in numpy; their parameter is read from GTSAM's own serialisation and the formulas are checked against the
estimator's ``weight`` and ``loss`` when the model is built (a mismatch — a future GTSAM, a subclass — falls back to
calling those). A kernel of your own made by `vectorised_estimator` (a ``Custom`` whose functions take arrays) runs
on arrays too, after the same check. Any other estimator (``mEstimator.Custom`` with scalar Python callbacks, the
asymmetric ones) runs from a table of its own values (`lfgraph.engine.kernel_table`: cubic interpolation checked
against the callbacks cell by cell to 1e-9, the callbacks answering where it does not match, e.g. at a kink); one that
is not finite everywhere is called per residual (about a microsecond per residual and iteration).
"""

from __future__ import annotations

import weakref
from collections.abc import Callable

import gtsam
import numpy as np

from lfgraph.engine.kernel_table import KernelTable

_M = gtsam.noiseModel.mEstimator
PROBE_DISTANCES = np.array([0.0, 0.05, 0.3, 0.9, 1.0, 1.7, 3.1, 7.5, 40.0])  # whitened distances the formulas are
PROBE_RTOL = 1e-9  # checked at against GTSAM's own weight and loss, to this relative tolerance
FAR_DISTANCES = np.array([1e4, 1e8])  # a kernel's loss is bounded (a redescender that ignores far residuals: Tukey,
BOUNDED_LOSS_RATIO = 1.01  # Geman–McClure, Welsch, DCS) when it grows by at most this much between these distances


class NotBulk(ValueError):
    """The noise model cannot be applied in bulk (not a 2-D Gaussian, optionally robust): use GTSAM's factors."""


def _huber(k: float):
    def weight(d):
        a = np.abs(d)
        return np.where(a <= k, 1.0, k / np.maximum(a, 1e-300))

    def loss(d):
        a = np.abs(d)
        return np.where(a <= k, 0.5 * a * a, k * (a - 0.5 * k))
    return weight, loss


def _cauchy(k: float):
    k2 = k * k
    return (lambda d: k2 / (k2 + d * d)), (lambda d: 0.5 * k2 * np.log1p(d * d / k2))


def _tukey(c: float):
    def weight(d):
        u = 1.0 - (d / c) ** 2
        return np.where(np.abs(d) <= c, u * u, 0.0)

    def loss(d):
        u = 1.0 - (d / c) ** 2
        return np.where(np.abs(d) <= c, c * c / 6.0 * (1.0 - u * u * u), c * c / 6.0)
    return weight, loss


def _geman_mcclure(c: float):
    c2 = c * c
    return (lambda d: c2 * c2 / (c2 + d * d) ** 2), (lambda d: 0.5 * c2 * d * d / (c2 + d * d))


def _dcs(c: float):
    def weight(d):
        e2 = d * d
        return np.where(e2 > c, (2.0 * c / (c + e2)) ** 2, 1.0)

    def loss(d):
        e2 = d * d
        return np.where(e2 > c, c * (3.0 * e2 - c) / (2.0 * (c + e2)), 0.5 * e2)
    return weight, loss


def _welsch(c: float):
    return (lambda d: np.exp(-(d / c) ** 2)), (lambda d: 0.5 * c * c * (1.0 - np.exp(-(d / c) ** 2)))


def _fair(c: float):
    return (lambda d: 1.0 / (1.0 + np.abs(d) / c)), \
        (lambda d: c * c * (np.abs(d) / c - np.log1p(np.abs(d) / c)))


def _null(_: float = 0.0):
    return (lambda d: np.ones_like(d)), (lambda d: 0.5 * d * d)


_FORMULAS: dict[type, Callable] = {_M.Huber: _huber, _M.Cauchy: _cauchy, _M.Tukey: _tukey,
                                   _M.GemanMcClure: _geman_mcclure, _M.DCS: _dcs, _M.Welsch: _welsch,
                                   _M.Fair: _fair, _M.Null: _null}


def _serialized_fields(estimator) -> list[float]:
    """The numbers of GTSAM's text serialisation after the archive header: the reweight scheme, then the
    estimator's parameters (e.g. Huber ``1 1.345``, Cauchy ``0 0.7 0.49``)."""
    try:
        body = estimator.serialize().splitlines()[1].split()
        return [float(x) for x in body[3:] if _is_number(x)]
    except Exception:  # noqa: BLE001  (an estimator without serialisation: probed instead)
        return []


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


_VECTORISED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # Custom estimator -> its array functions


def vectorised_estimator(weight: Callable[[np.ndarray], np.ndarray], loss: Callable[[np.ndarray], np.ndarray],
                         scheme: str = "block") -> gtsam.noiseModel.mEstimator.Custom:
    """A robust kernel of your own as a GTSAM ``mEstimator.Custom`` whose functions also take arrays: GTSAM's
    factors call them one distance at a time, the bulk solvers (`Kernel`) call them on every residual at once — the
    speed of the built-in kernels and exact, where a ``Custom`` made from scalar callbacks runs from a table of its
    values (`lfgraph.engine.kernel_table`, to 1e-9).

    Args:
        weight, loss: w(d) and rho(d) of whitened distances d >= 0, numpy in and out (e.g. ``lambda d: 1 / (1 +
            d * d)``); checked against their own calls on single distances when the bulk solver first uses them.
        scheme: ``"block"`` (GTSAM's default: one weight for both coordinates of a residual) or ``"scalar"``.

    Raises:
        ValueError: an unknown scheme.
    """
    schemes = {"block": _M.Base.ReweightScheme.Block, "scalar": _M.Base.ReweightScheme.Scalar}
    if scheme not in schemes:
        raise ValueError(f"scheme must be 'block' or 'scalar', got {scheme!r}")
    _check_kernel(weight, loss)
    estimator = _M.Custom.Create(lambda d: float(weight(np.float64(d))), lambda d: float(loss(np.float64(d))),
                                 reweight=schemes[scheme])
    _VECTORISED[estimator] = (weight, loss)
    return estimator


KERNEL_PROBE = np.array([0.0, 0.5, 1.0, 2.0, 5.0, 50.0])  # whitened distances a user's kernel is tried at


def _check_kernel(weight: Callable, loss: Callable) -> None:
    """A user's kernel, refused at its door unless w(d) and rho(d) are callables giving finite values >= 0 at single
    distances (`KERNEL_PROBE`, one at a time, as GTSAM calls them; whether they also take arrays is found out when
    the bulk solver first uses them)."""
    for name, fn in (("weight", weight), ("loss", loss)):
        if not callable(fn):
            raise TypeError(f"vectorised_estimator: {name} must be a function of the distance, got "
                            f"{type(fn).__name__}")
        try:
            values = np.array([float(fn(np.float64(d))) for d in KERNEL_PROBE])
        except Exception as exc:  # noqa: BLE001  (the user's function: say what it did)
            raise ValueError(f"vectorised_estimator: {name}(d) failed on a distance: {exc}") from None
        if not np.all(np.isfinite(values)) or np.any(values < 0):
            raise ValueError(f"vectorised_estimator: {name}(d) must be finite and >= 0; at d = "
                             f"{KERNEL_PROBE.tolist()} it gave {values.tolist()}")


_TABLES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # estimator -> its tables, or None


def _tables(estimator) -> tuple[KernelTable, KernelTable] | None:
    """Tables of an estimator's weight and loss (`lfgraph.engine.kernel_table`), built once per estimator; None when it
    cannot be tabulated (not finite, raises) or cannot be remembered (then it is called per residual)."""
    try:
        if estimator in _TABLES:
            return _TABLES[estimator]
    except TypeError:  # not weakly referenceable
        return None
    try:
        tables = (KernelTable(estimator.weight), KernelTable(estimator.loss))
    except Exception:  # noqa: BLE001  (a function that fails somewhere: called per residual, as GTSAM does)
        tables = None
    _TABLES[estimator] = tables
    return tables


def _on_arrays(f: Callable) -> Callable[[np.ndarray], np.ndarray]:
    """``f`` of an array of distances, its result float64 of the same shape (a constant broadcast)."""
    def g(d):
        d = np.asarray(d, dtype=np.float64)
        return np.broadcast_to(np.asarray(f(d), dtype=np.float64), d.shape)
    return g


class Kernel:
    """One GTSAM M-estimator as vectorised ``weight(d)`` and ``loss(d)`` of whitened distances, and its scheme.

    Args:
        estimator: any ``gtsam.noiseModel.mEstimator`` object.

    Attributes:
        block: GTSAM's Block reweighting (both rows of a residual by one weight), else Scalar.
        vectorised: it is evaluated on arrays: the built-in kernels' formulas in numpy, a `vectorised_estimator`'s
            functions, or (``tabulated``) a `lfgraph.engine.kernel_table.KernelTable` of a ``Custom``'s scalar
            callbacks; else the estimator is called per residual.
        bounded: the loss is bounded (Tukey, Geman–McClure, Welsch, DCS): a residual far beyond the threshold pulls
            nothing, so a fit must start near its minimum.
    """

    def __init__(self, estimator):
        self.estimator = estimator
        self.block = self._is_block(estimator)
        self.vectorised = False
        fields = _serialized_fields(estimator)
        make = _FORMULAS.get(type(estimator))
        if make is not None and (len(fields) >= 2 or make is _null):
            weight, loss = make(fields[1]) if make is not _null else make()
            if self._agrees(weight, loss):
                self.weight, self.loss, self.vectorised = weight, loss, True
        arrays = _VECTORISED.get(estimator) if make is None else None
        if arrays is not None:  # a kernel of the user's own, given as array functions (`vectorised_estimator`)
            weight, loss = (_on_arrays(f) for f in arrays)
            try:
                same = self._agrees(weight, loss)
            except Exception:  # noqa: BLE001  (functions that do not take arrays after all: called per residual)
                same = False
            if same:
                self.weight, self.loss, self.vectorised = weight, loss, True
        self.tabulated = False
        if not self.vectorised:  # scalar callbacks: from a table of their values where it matches them, else per call
            tables = _tables(estimator)
            if tables is not None:
                (self.weight, self.loss), self.vectorised, self.tabulated = tables, True, True
            else:
                self.weight = np.frompyfunc(estimator.weight, 1, 1)
                self.loss = np.frompyfunc(estimator.loss, 1, 1)
        far = self.losses(FAR_DISTANCES)
        self.bounded = bool(np.isfinite(far[1]) and far[1] <= BOUNDED_LOSS_RATIO * far[0])

    @staticmethod
    def _is_block(estimator) -> bool:
        """GTSAM's reweight scheme, read off its whitening of one residual (Block scales both rows alike)."""
        model = gtsam.noiseModel.Robust.Create(estimator, gtsam.noiseModel.Unit.Create(2))
        v = np.array([3.0, 0.2])
        w = np.asarray(model.whiten(v))
        return bool(np.isclose(w[0] * v[1], w[1] * v[0], rtol=1e-9, atol=1e-15))

    def _agrees(self, weight, loss) -> bool:
        d = PROBE_DISTANCES
        mine_w, mine_l = np.asarray(weight(d), float), np.asarray(loss(d), float)
        theirs_w = np.array([self.estimator.weight(float(x)) for x in d])
        theirs_l = np.array([self.estimator.loss(float(x)) for x in d])
        return bool(np.allclose(mine_w, theirs_w, rtol=PROBE_RTOL, atol=1e-12)
                    and np.allclose(mine_l, theirs_l, rtol=PROBE_RTOL, atol=1e-12))

    def weights(self, d: np.ndarray) -> np.ndarray:
        """w(d) of whitened distances ``d`` (array), as float64."""
        return np.asarray(self.weight(d), dtype=np.float64)

    def losses(self, d: np.ndarray) -> np.ndarray:
        """loss(d) of whitened distances ``d`` (array), as float64: the factor error GTSAM adds per residual."""
        return np.asarray(self.loss(d), dtype=np.float64)


class BulkNoise:
    """A 2-D GTSAM measurement noise model (any Gaussian, optionally inside ``noiseModel.Robust``) for (M, 2)
    residuals at once.

    Attributes:
        sqrt_information: (2, 2) ``R`` of the Gaussian part (whitened = R r).
        isotropic_sigma: its sigma when isotropic (then R = I / sigma), else None.
        kernel: the `Kernel` of a robust model, None for a Gaussian one.

    Raises:
        NotBulk: a model of another dimension, a constrained model or another kind (GTSAM's factors are needed).
    """

    def __init__(self, model: gtsam.noiseModel.Base):
        base, estimator = model, None
        if isinstance(model, gtsam.noiseModel.Robust):
            base, estimator = model.noise(), model.robust()
        if not isinstance(base, gtsam.noiseModel.Gaussian) or base.dim() != 2 or base.isConstrained():
            raise NotBulk(f"{type(base).__name__} of dimension {base.dim()} is not a 2-D Gaussian model")
        self.model = model
        self.sqrt_information = np.asarray(base.R(), dtype=np.float64)
        self.isotropic_sigma: float | None = None
        if isinstance(base, gtsam.noiseModel.Isotropic):
            self.isotropic_sigma = float(base.sigma())
        self.kernel = Kernel(estimator) if estimator is not None else None

    def whiten(self, r: np.ndarray) -> np.ndarray:
        """(M, 2) residuals (or (M, 2, k) Jacobians) whitened by the Gaussian part."""
        if self.isotropic_sigma is not None:
            return r / self.isotropic_sigma
        return np.einsum("ij,mj...->mi...", self.sqrt_information, r)

    def sqrt_weights(self, e: np.ndarray) -> np.ndarray | None:
        """(M, 2) factors by which GTSAM scales each whitened row (None: a Gaussian model, all ones)."""
        if self.kernel is None:
            return None
        if self.kernel.block:
            return np.repeat(np.sqrt(self.kernel.weights(np.hypot(e[:, 0], e[:, 1])))[:, None], 2, axis=1)
        return np.sqrt(self.kernel.weights(e))

    def cost(self, e: np.ndarray) -> float:
        """Sum of the factors' errors for (M, 2) whitened residuals (GTSAM's ``graph.error`` of these factors)."""
        if self.kernel is None:
            return 0.5 * float(np.sum(e * e))
        if not self.kernel.block:  # GTSAM's factor error with the Scalar scheme: the loss of each component
            return float(np.sum(self.kernel.losses(np.abs(e))))
        return float(np.sum(self.kernel.losses(np.hypot(e[:, 0], e[:, 1]))))
