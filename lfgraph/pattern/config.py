"""Options of pattern calibration, typed and parsed once."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from lfgraph.factors.hooks import as_hooks
from lfgraph.factors.noise import Noise, NoiseSpec, as_noise
from lfgraph.lenses import lens_model, lens_names


class Method(StrEnum):
    """Which route calibrates."""

    JOINT = "joint"  # one GTSAM graph over all views and frames
    PAPER = "paper"  # per-view Zhang + relative PnP/LM, as in the paper


class Init(StrEnum):
    """Where the joint route starts."""

    PAPER = "paper"  # the paper route's result
    DESIGN = "design"  # design values: focal length, centred principal point, no distortion, ideal grid or PnP


AUTO_LENS = "auto"  # a view's lens chosen by held-out frames (`lfgraph.pattern.lenses.choose_lenses`)


def parse_lens_spec(spec: str | Mapping[str | int, str]) -> tuple[str, dict[str | int, str]]:
    """(default model, {view name or index: model}) of a lens choice: ``"auto"``, one model name, a mapping of views
    to models, or the CLI's ``"auto,r00_c02=fisheye"`` (one default, then per-view ones). ValueError naming what is
    wrong: an unknown model, two defaults, a view given twice (views are checked against a grid later)."""
    choices = (AUTO_LENS, *lens_names())
    default, per_view, given = AUTO_LENS, {}, []
    if isinstance(spec, str):
        defaults = []
        for token in (t.strip() for t in spec.split(",") if t.strip()):
            name, eq, lens = token.partition("=")
            if eq:
                given.append(name.strip())
                per_view[name.strip()] = lens.strip()
            else:
                defaults.append(token)
        if len(defaults) > 1:
            raise ValueError(f"lens: one default model, then VIEW=MODEL pairs; got {', '.join(defaults)}")
        default = defaults[0] if defaults else AUTO_LENS
    elif isinstance(spec, Mapping):
        per_view = dict(spec)
        given = list(per_view)
    else:
        raise TypeError(f"lens must be a model name or a mapping of views to models, got {type(spec).__name__}")
    twice = sorted({str(k) for k in given if given.count(k) > 1})
    if twice:
        raise ValueError(f"lens: view {', '.join(twice)} given more than once")
    if default not in choices:
        raise ValueError(f"unknown lens {default!r}; choose from {', '.join(choices)}")
    for key, lens in per_view.items():
        if lens not in choices:
            raise ValueError(f"lens for {key}: unknown model {lens!r}; choose from {', '.join(choices)}")
    return default, per_view


@dataclass(frozen=True)
class CalibrateConfig:
    """Options of `lfgraph.calibrate`. Everything is validated and normalised on construction.

    Attributes:
        method: ``joint`` (default) or ``paper``.
        init: start of the joint route: ``paper`` or ``design``.
        focal_px, pitch_mm: design values for ``init="design"`` (default: the larger image side; PnP-averaged poses).
        robust: the corner noise model: a kernel name (``"huber:1.0"``: threshold in pixels; ``"cauchy"``: its usual
            constant in sigmas; ``"none"``), a `RobustKernel`, a ``gtsam.noiseModel.mEstimator`` object (threshold
            in corner sigmas) or a full ``gtsam`` noise model.
        corner_sigma_px: the measurement model's corner noise; sets the scale of robust thresholds and of the
            board prior's weight. Reported uncertainties are rescaled by the noise estimated from the residuals.
        tangential: estimate p1, p2 (held at 0 otherwise, the paper's model).
        board_sigma_mm: board non-flatness tolerance; None treats the board as rigid and flat.
        max_iterations: Levenberg–Marquardt cap.
        marginals: compute 1-sigma uncertainties (costs ~0.2 s for 4x4x40).
        graph_hooks: user functions called with a `lfgraph.factors.GraphContext` before the joint graph is
            optimised (add your own factors or priors; see `lfgraph.factors.hooks`).
        screen: without a ``robust`` kernel, first a robust (Cauchy, 1 px) fit that drops the view-frames the rig
            cannot explain (swapped or mis-detected images), by name; False fits every observation by least squares.
        lens: each view's lens model: ``"auto"`` (default: per view, the model that predicts held-out frames best),
            ``"radtan"`` or ``"fisheye"`` for every view, or per view: ``"auto,r00_c02=fisheye"`` or a mapping
            ``{"r00_c02": "fisheye"}`` (views by name or index; the others auto).
        check_grid: hold the result against its grid (`lfgraph.pattern.design_check`): a mirrored view, two views
            at one place (a duplicated stream), views each at the other's place (swapped cables) or off the grid are
            refused by name; False for a rig that is deliberately no grid (it still may not be mirrored).
    """

    method: Method | str = Method.JOINT
    init: Init | str = Init.PAPER
    focal_px: float | None = None
    pitch_mm: float | None = None
    robust: NoiseSpec = None
    corner_sigma_px: float = 1.0
    tangential: bool = False
    board_sigma_mm: float | None = None
    max_iterations: int = 100
    marginals: bool = True
    graph_hooks: tuple[Callable, ...] = ()
    lens: str | Mapping[str | int, str] = "auto"
    screen: bool = True
    check_grid: bool = True

    def __post_init__(self) -> None:
        for name, kind in (("method", Method), ("init", Init)):
            try:
                object.__setattr__(self, name, kind(getattr(self, name)))
            except ValueError:
                raise ValueError(f"unknown {name} {getattr(self, name)!r}; choose from {', '.join(kind)}") from None
        object.__setattr__(self, "robust", as_noise(self.robust))
        object.__setattr__(self, "graph_hooks", as_hooks(self.graph_hooks, "CalibrateConfig.graph_hooks"))
        default, per_view = parse_lens_spec(self.lens)
        named = {default, *per_view.values()} - {AUTO_LENS}
        if self.tangential and named and AUTO_LENS not in {default, *per_view.values()} and \
                not any(lens_model(m).tangential for m in named):
            raise ValueError(f"tangential: a {' or '.join(sorted(named))} lens has no tangential distortion (p1, p2)")
        for name, largest in (("board_sigma_mm", 100.0), ("focal_px", 1e6), ("pitch_mm", 1e6)):
            value = getattr(self, name)
            if value is not None and not (np.isfinite(value) and 0 < value <= largest):
                raise ValueError(f"{name} must be positive and at most {largest:g}, got {value}")
        if not (np.isfinite(self.corner_sigma_px) and self.corner_sigma_px > 0):
            raise ValueError(f"corner_sigma_px must be positive, got {self.corner_sigma_px}")

    @property
    def noise(self) -> Noise:
        """The normalised corner noise model (``robust`` after `as_noise`)."""
        return self.robust  # type: ignore[return-value]

    @property
    def pitch_m(self) -> float | None:
        """``pitch_mm`` in metres (None when not given)."""
        return None if self.pitch_mm is None else self.pitch_mm / 1000.0
