"""The lens models, one module each (`radtan`, `fisheye`, `unified`), and their registry.

A model is a `LensModel` (`lfgraph.lenses.model`): its coefficients, its GTSAM calibration class (every factor of
it follows by name), its distortion with Jacobian and inverse, where it folds, its OpenCV form. Everything in
lfgraph that depends on the lens asks the registry (``lens_model(intr.lens)``) rather than naming a model. Adding a
model is one module with a ``MODEL`` and one line in `_BUILT_IN` (or `register` from outside the package); its
coefficients are among `COEFFICIENTS` (the fields of `lfgraph.core.camera.Intrinsics`).
"""

from __future__ import annotations

import numpy as np

from lfgraph.lenses import fisheye, radtan, unified
from lfgraph.lenses.model import COEFFICIENTS, HEAD, LensModel

__all__ = ["COEFFICIENTS", "DEFAULT_LENS", "FISHEYE", "HEAD", "RADTAN", "UNIFIED", "LensModel",
           "lens_coefficient_jacobian", "lens_distort", "lens_model", "lens_names", "register"]

_BUILT_IN = (radtan.MODEL, fisheye.MODEL, unified.MODEL)  # one line per model, in code order (never reordered)
_MODELS: dict[str, LensModel] = {}
DEFAULT_LENS = radtan.MODEL.name  # a view whose lens is not said (files before lens models; Intrinsics(...))
RADTAN, FISHEYE, UNIFIED = radtan.MODEL.name, fisheye.MODEL.name, unified.MODEL.name  # the built-in models' names


def register(model: LensModel) -> None:
    """Make ``model`` known by its name (a new name only; its code is its place in registration order)."""
    if model.name in _MODELS:
        raise ValueError(f"a lens model named {model.name!r} is registered already")
    unknown = set(model.coefficients) - set(COEFFICIENTS)
    if unknown or set(model.tangent) != set(model.coefficients):
        raise ValueError(f"lens model {model.name}: coefficients must be among {COEFFICIENTS} and the tangent must "
                         f"name the same ones, got {model.coefficients} and {model.tangent}")
    _MODELS[model.name] = model


for _model in _BUILT_IN:
    register(_model)


def lens_names() -> tuple[str, ...]:
    """The registered models' names, in code order (`lens_code`)."""
    return tuple(_MODELS)


def lens_model(name: str) -> LensModel:
    """The registered model called ``name``; ValueError naming the known ones."""
    try:
        return _MODELS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown lens model {name!r}: one of {', '.join(_MODELS)}") from None


def lens_code(name: str) -> int:
    """A model's index in registration order (the bulk solvers' per-view lens code)."""
    return lens_names().index(lens_model(name).name)


def lens_distort(code: np.ndarray, coef: np.ndarray, x: np.ndarray, y: np.ndarray,
                 jacobian: bool = False) -> tuple[np.ndarray, ...]:
    """Each point's own lens applied to normalised coordinates, all models at once.

    Args:
        code: lens of each point (`lens_code`: 0 radtan, 1 fisheye, 2 unified, ...); same shape as ``x``.
        coef: (7, *x.shape) k1, k2, p1, p2, k3, k4, xi of each point's lens (`COEFFICIENTS`).
        x, y: undistorted normalised coordinates.
        jacobian: also return the Jacobian of the map.

    Returns:
        (xd, yd), or (xd, yd, d xd/dx, d xd/dy, d yd/dx, d yd/dy) with ``jacobian``.
    """
    out = [np.empty(np.shape(x)) for _ in range(6 if jacobian else 2)]
    for c, model in enumerate(_MODELS.values()):
        m = code == c
        if m.all():  # one model for every point: no gather and scatter
            return tuple(model.bulk_map(x, y, *coef, jacobian=jacobian))
        if m.any():
            for o, value in zip(out, model.bulk_map(x[m], y[m], *(k[m] for k in coef), jacobian=jacobian),
                                strict=True):
                o[m] = value
    return tuple(out)


def lens_coefficient_jacobian(code: np.ndarray, coef: np.ndarray, x: np.ndarray, y: np.ndarray,
                              width: int) -> np.ndarray:
    """Each point's d (xd, yd) / d (its lens's coefficients, tangent order), all models at once: (*x.shape, 2,
    ``width``), zero-padded beyond a model's own coefficients. Arguments as `lens_distort`.

    Raises:
        ValueError: a model without ``coefficient_jacobian`` (or with more coefficients than ``width``).
    """
    out = np.zeros((*np.shape(x), 2, width))
    for c, model in enumerate(_MODELS.values()):
        m = code == c
        if m.any():
            if model.coefficient_jacobian is None or len(model.tangent) > width:
                raise ValueError(f"lens model {model.name} has no coefficient Jacobian of width <= {width}")
            if m.all():  # one model for every point: no gather and scatter
                out[..., :len(model.tangent)] = model.coefficient_jacobian(x, y, *coef)
                break
            out[m, :, :len(model.tangent)] = model.coefficient_jacobian(x[m], y[m], *(k[m] for k in coef))
    return out
