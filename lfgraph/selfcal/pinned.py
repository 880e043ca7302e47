"""The pinned final stage of a self-calibration: the scene's final graph plus each pin's factors, the zoom's sigma
with and without each pin, and the refusal of a pin that disagrees with the scene beyond their sigmas.

A pin's test is that of nested estimates in the space of the weakly seen modes (`report.modes`: the common zoom,
the common principal-point shift and the hidden principal-point gauge's slopes). The scene alone gives them m0 with
covariance S0, the scene and the pin m1 with S1; when both are right, m1 - m0 is Gaussian with covariance S0 - S1
(the information the pin added). In S0's whitened coordinates the pin removed a fraction l of the variance along
each eigen-direction of S0 - S1; over the directions where it removed at least `INFORMED_SHARE`, the shift's
chi-square (degrees of freedom: their number) is the disagreement, as a one-sided normal deviate. A pin beyond
`PIN_DISAGREEMENT_SIGMAS` is refused by name: a mismeasured distance, a board of another square size, another
camera's calibration. A distance fixes one combination of the two near-gauges (the common zoom scales depths, the
hidden gauge shifts inverse depths): which one it mostly fixes depends on which the scene holds better.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import gtsam
import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.observer import Observer
from lfgraph.core.sigmas import Sigmas
from lfgraph.engine.stage_engine import FINAL_RELATIVE_TOL
from lfgraph.factors.keys import pin_point_key
from lfgraph.factors.noise import RobustKernel
from lfgraph.factors.selfcal_graph import design_tangent_sigmas
from lfgraph.refinement.posterior import chi2_sigma
from lfgraph.selfcal.pins import BoardPin, DistancePin, Pin, PinError, ViewPin
from lfgraph.selfcal.report import Mode, modes
from lfgraph.selfcal.solve import LANDMARK_ITERATIONS, measurement, posterior, run_map_stage
from lfgraph.selfcal.stages import reachable

PIN_DISAGREEMENT_SIGMAS = 3.0  # a pin whose shift of the weak modes is beyond this deviate (p ~ 0.001) is refused
INFORMED_SHARE = 0.1  # the test's directions: those along which the pin removed at least this share of the variance
FIXES_ZOOM = 0.5  # a pin "fixes the zoom" when the zoom's sigma with it is below this fraction of the scene's alone
UNCHECKED_PCT = 5.0  # a pin whose measurement the scene can check only beyond this mistake (%) is warned about: a tape
# read a few per cent wrong, or a mark on the wrong point, would pass unnoticed
PIN_ITERATIONS = 100  # Levenberg–Marquardt cap of a pinned fit (it starts at the scene's optimum)
REACH_PASSES = 3  # a pinned fit is run again without the landmarks it pushed out of reach, at most this often


class PinRefused(PinError):
    """A pin disagrees with the scene beyond their sigmas; the message names it and the disagreement in sigmas."""


@dataclass(frozen=True)
class PinResult:
    """What one pin did to the common zoom (the mean focal length over views, px).

    Attributes:
        name, kind: the pin (``board``, ``distance``, ``view``); description: what it measures.
        scene_zoom_px, scene_sigma_px: the zoom and its posterior sigma from the scene and design alone.
        zoom_px, sigma_px: with the pin (the scene's graph and this pin only).
        disagreement_sigmas: how far the pin disagrees with the scene, as a one-sided normal deviate (module
            docstring), large when they disagree.
        residual: the pin's own fit (e.g. the fitted distance against the measured, in its sigmas).
        check_pct: the mistake in the pin's measurement (its distance, or its view's focal length), relative, in %, that
            alone would bring the test to `PIN_DISAGREEMENT_SIGMAS` (`check_pct`): a mistake well below it passes
            unnoticed, one well beyond is refused (the right measurement's own noise moves the line a little). None
            for a board pin.
    """

    name: str
    kind: str
    description: str
    scene_zoom_px: float
    scene_sigma_px: float
    zoom_px: float
    sigma_px: float
    disagreement_sigmas: float
    residual: str
    check_pct: float | None = None

    @property
    def fixes_zoom(self) -> bool:
        """Whether the pin, not the design, set the zoom (its sigma below `FIXES_ZOOM` of the scene's)."""
        return bool(self.sigma_px < FIXES_ZOOM * self.scene_sigma_px)

    def as_dict(self) -> dict:
        """The fields and ``fixes_zoom`` as a JSON-ready dict."""
        return {"name": self.name, "kind": self.kind, "description": self.description,
                "scene_zoom_px": self.scene_zoom_px, "scene_sigma_px": self.scene_sigma_px, "zoom_px": self.zoom_px,
                "sigma_px": self.sigma_px, "disagreement_sigmas": self.disagreement_sigmas,
                "fixes_zoom": self.fixes_zoom, "residual": self.residual, "check_pct": self.check_pct}

    def text(self) -> str:
        """One line for the report."""
        pct = 100.0 / self.scene_zoom_px
        verb = "fixes the zoom" if self.fixes_zoom else "adds little to the zoom"
        return (f"pin {self.name} ({self.description}) {verb}: sigma {self.scene_sigma_px:.3g} px "
                f"({pct * self.scene_sigma_px:.2g} %) without it, {self.sigma_px:.3g} px "
                f"({pct * self.sigma_px:.2g} %) with it; it moved the zoom {self.zoom_px - self.scene_zoom_px:+.3g} px "
                f"(disagreement {self.disagreement_sigmas:.2f} sigma); {self.residual}{self.check_text()}")

    def check_text(self) -> str:
        """How precisely the scene could check the pin's measurement, in words ('' for a board pin)."""
        if self.check_pct is None:
            return ""
        what = "focal length" if self.kind == "view" else "distance"
        return (f"; the scene can check this {what} only to about {self.check_pct:.2g} %: a mistake well below "
                f"that passes unnoticed")


def pin_kind(pin: Pin) -> str:
    """``board``, ``distance`` or ``view``."""
    return {BoardPin: "board", DistancePin: "distance", ViewPin: "view"}[type(pin)]


def zoom_of(calib: Calibration, joint: np.ndarray, sigmas: Sigmas, distortion: bool) -> tuple[float, float]:
    """The common zoom (mean of every view's fx and fy, px) and its posterior sigma from the (DV, DV) ``joint``."""
    zoom = float(np.mean([[i.fx, i.fy] for i in calib.intrinsics]))
    mode: Mode = modes(joint, design_tangent_sigmas(sigmas)[calib.grid.reference], calib.grid, distortion)[0]
    return zoom, mode.posterior_sigma


@dataclass(frozen=True)
class SceneFit:
    """The scene's final stage, where the pins start: calibration, (N, 3) landmarks, tracks (`PooledTracks`), the
    groups freed, the design priors and calibration, the measured noise, its zoom and sigma, and its weak modes'
    values and covariance (`weak_modes`: what a pin is tested on)."""

    calib: Calibration
    nominal: Calibration
    points: np.ndarray
    tracks: object
    free: frozenset
    sigmas: Sigmas
    noise_px: float
    zoom_px: float
    zoom_sigma_px: float
    modes: np.ndarray | None = None
    modes_cov: np.ndarray | None = None


def _fit(scene: SceneFit, pins: Sequence[Pin], max_iterations: int, hooks: tuple[Callable, ...],
         say: Observer):
    """The scene's final graph with ``pins``' factors, from the scene's optimum: (calibration, landmarks, graph,
    values, the pins' fragments).

    A pin moves the near-gauges within what the scene allows, and the hidden principal-point gauge shifts every
    landmark's inverse depth: the farthest can be pushed to infinity and beyond, where they hold nothing and leave
    the system indeterminate. Those are dropped (`reachable`) and the fit is run again from the scene's optimum
    without them, as the scene's own final stage drops them."""
    tracks, points = scene.tracks, scene.points
    focal = float(np.mean([i.fx for i in scene.nominal.intrinsics]))
    for _ in range(REACH_PASSES):
        fit = _fit_once(scene, tracks, points, pins, max_iterations, hooks, say)
        keep = reachable(fit[0], fit[1], tracks.valid, focal)
        if keep.all():
            break
        say.log(f"self-calibration: {int((~keep).sum())} landmark(s) pushed out of reach by the pins dropped")
        tracks, points = tracks.subset(keep), points[keep]
    return fit


def _fit_once(scene: SceneFit, tracks, points: np.ndarray, pins: Sequence[Pin], max_iterations: int,
              hooks: tuple[Callable, ...], say: Observer):
    fragments: list[gtsam.NonlinearFactorGraph] = []

    def add_pins(ctx) -> None:
        fragments.clear()
        for k, pin in enumerate(pins):
            fragment = pin.factors(ctx.calib, ctx.initial, scene.noise_px, 2 * k)
            fragments.append(fragment)
            ctx.graph.push_back(fragment)

    calib, points, graph, values, _ = run_map_stage(
        scene.calib, scene.nominal, tracks.pixels, tracks.valid, points, scene.free, scene.sigmas,
        measurement(RobustKernel("none"), scene.noise_px), max_iterations, FINAL_RELATIVE_TOL, say.iteration,
        (*hooks, add_pins), hold_gauges=False, landmark_iterations=LANDMARK_ITERATIONS)
    return calib, points, graph, values, list(fragments)


def _residual(pin: Pin, k: int, calib: Calibration, values: gtsam.Values, fragment: gtsam.NonlinearFactorGraph) -> str:
    """The pin's own fit, in words."""
    if isinstance(pin, DistancePin):
        d, z = pin.fitted_distance_m(values, 2 * k)
        depth = "" if pin.depth_m is None else \
            f", fitted depth {z:.4f} m vs {pin.depth_m:.4f} m ({(z - pin.depth_m) / pin.depth_sigma_m:+.2f} sigma)"
        return (f"fitted distance {d:.4f} m vs {pin.distance_m:.4f} m measured "
                f"({(d - pin.distance_m) / pin.sigma_m:+.2f} sigma){depth}")
    if isinstance(pin, ViewPin):
        fx = calib.intrinsics[pin.view].fx
        return (f"fitted fx {fx:.2f} px vs {pin.intrinsics.fx:.2f} px pinned "
                f"({(fx - pin.intrinsics.fx) / pin.sigmas[0]:+.2f} sigma)")
    n = int(pin.valid.sum())
    chi2 = 2.0 * float(fragment.error(values))
    return f"corner residual {np.sqrt(max(chi2, 0.0) / (2 * n)):.2f} of the corner sigma over {n} corners"


def mode_rows(grid, n: int, dim: int) -> np.ndarray:
    """(M, dim n) the weak modes as rows over every view's calibration (``dim`` coordinates each, Cal3DS2's tangent
    order): the zoom (mean of fx and fy), the common cx and cy shift, cx per grid column and cy per grid row."""
    off = np.array([grid.offset(v) for v in range(n)], dtype=float)
    rows = [{0: np.full(n, 0.5 / n), 1: np.full(n, 0.5 / n)}, {3: np.full(n, 1.0 / n)}, {4: np.full(n, 1.0 / n)}]
    for axis, idx in ((1, 3), (0, 4)):
        d = off[:, axis] - off[:, axis].mean()
        if np.sum(d**2) > 0:
            rows.append({idx: d / np.sum(d**2)})
    a = np.zeros((len(rows), dim * n))
    for k, row in enumerate(rows):
        for idx, w in row.items():
            a[k, idx::dim] = w
    return a


def weak_modes(calib: Calibration, joint: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The weak modes' values (the zoom, the common cx and cy shift, cx per grid column and cy per grid row; px)
    and their covariance, from ``calib`` and the (DV, DV) ``joint`` covariance of every view's calibration."""
    n = calib.num_views
    dim = len(joint) // n
    a = mode_rows(calib.grid, n, dim)
    theta = np.zeros(dim * n)
    for idx, name in ((0, "fx"), (1, "fy"), (3, "cx"), (4, "cy")):
        theta[idx::dim] = [getattr(i, name) for i in calib.intrinsics]
    return a @ theta, a @ joint @ a.T


def _shift_chi2(scene: SceneFit, shift: np.ndarray, cov: np.ndarray) -> tuple[float, int]:
    """The test's chi-square of a shift of the weak modes and its degrees of freedom (`disagreement`)."""
    s0 = scene.modes_cov
    lam0, u0 = np.linalg.eigh(s0)
    w = u0 @ np.diag(1.0 / np.sqrt(np.maximum(lam0, 1e-30))) @ u0.T  # S0^(-1/2)
    removed, u = np.linalg.eigh(np.eye(len(s0)) - w @ cov @ w)
    keep = removed >= INFORMED_SHARE
    if not keep.any():
        return 0.0, 0
    proj = u[:, keep].T @ (w @ shift)
    return float(np.sum(proj**2 / removed[keep])), int(keep.sum())


def disagreement(scene: SceneFit, values: np.ndarray, cov: np.ndarray) -> float:
    """The nested test of the module docstring: the pin's shift of the weak modes against the variance it removed,
    as a one-sided normal deviate (0 when it removed none)."""
    return chi2_sigma(*_shift_chi2(scene, values - scene.modes, cov))


def check_pct(scene: SceneFit, cov: np.ndarray, gain: np.ndarray) -> float:
    """`PinResult.check_pct`: the relative mistake in a pin's measurement that the test refuses. A mistake e (a
    share of the measured value) shifts the pinned fit's weak modes by e ``gain`` (linearised: the posterior's
    covariance of the modes with the measured quantity over the pin's variance, times the value); the test's
    chi-square grows as e^2 and reaches `PIN_DISAGREEMENT_SIGMAS` (Wilson–Hilferty's inverse) at the figure returned,
    in % (inf when the pin moves no tested mode)."""
    chi2, dof = _shift_chi2(scene, gain, cov)
    if dof == 0 or chi2 <= 0:
        return float("inf")
    a = 2.0 / (9.0 * dof)
    limit = dof * (PIN_DISAGREEMENT_SIGMAS * np.sqrt(a) + 1.0 - a) ** 3
    return float(100.0 * np.sqrt(limit / chi2))


def _check(scene: SceneFit, pin: Pin, k: int, calib: Calibration, values: gtsam.Values, joint: np.ndarray,
           modes: np.ndarray, cov: np.ndarray) -> float | None:
    """`PinResult.check_pct` of a distance pin (a mistake in its distance) or a view pin (in its fx and fy); None for a
    board pin. ``joint``: the pinned fit's covariance of every view's calibration and, for a distance pin, of its
    two points (the last six coordinates); ``modes``: (M, DV) the weak modes' rows (`weak_modes`)."""
    n = len(joint)
    weights = np.zeros(n)  # each measured coordinate's value over its variance: a mistake e moves it by e x value
    if isinstance(pin, DistancePin):
        a, b = (np.asarray(values.atPoint3(pin_point_key(2 * k + i))) for i in range(2))
        weights[-6:] = np.concatenate([a - b, b - a]) / np.linalg.norm(a - b) * pin.distance_m / pin.sigma_m**2
    elif isinstance(pin, ViewPin):  # its focal length: fx and fy together (Cal3DS2's tangent order starts fx, fy)
        first = (modes.shape[1] // calib.num_views) * pin.view
        weights[first] = pin.intrinsics.fx / pin.sigmas[0] ** 2
        weights[first + 1] = pin.intrinsics.fy / pin.sigmas[1] ** 2
    else:
        return None
    rows = np.zeros((len(modes), n))
    rows[:, :modes.shape[1]] = modes
    return check_pct(scene, cov, rows @ joint @ weights)


def _result(scene: SceneFit, pin: Pin, k: int, fit, distortion: bool) -> PinResult:
    calib, _, graph, values, fragments = fit
    points = (pin_point_key(2 * k), pin_point_key(2 * k + 1)) if isinstance(pin, DistancePin) else ()
    joint_all = posterior(graph, values, calib.lenses, points)[1]
    joint = joint_all[:len(joint_all) - 3 * len(points), :len(joint_all) - 3 * len(points)]
    zoom, sigma = zoom_of(calib, joint, scene.sigmas, distortion)
    rows = mode_rows(calib.grid, calib.num_views, len(joint) // calib.num_views)
    values_m, cov = weak_modes(calib, joint)
    return PinResult(pin.name, pin_kind(pin), pin.describe(), scene.zoom_px, scene.zoom_sigma_px, zoom, sigma,
                     disagreement(scene, values_m, cov), _residual(pin, k, calib, values, fragments[k]),
                     _check(scene, pin, k, calib, values, joint_all, rows, cov))


def pin_warnings(results: Sequence[PinResult]) -> list[str]:
    """The report's warnings for pins the scene cannot check to `UNCHECKED_PCT`."""
    return [f"pin {r.name} could not be checked: the scene can check its "
            f"{'focal length' if r.kind == 'view' else 'distance'} only to about {r.check_pct:.2g} % (a mistake well "
            f"below that passes unnoticed); make sure of the measurement"
            for r in results if r.check_pct is not None and r.check_pct > UNCHECKED_PCT]


def _refuse(result: PinResult) -> None:
    """Raises PinRefused when the pin disagrees with the scene beyond `PIN_DISAGREEMENT_SIGMAS`."""
    if result.disagreement_sigmas <= PIN_DISAGREEMENT_SIGMAS:
        return
    pct = 100.0 * (result.zoom_px - result.scene_zoom_px) / result.scene_zoom_px
    raise PinRefused(f"pin {result.name} disagrees with the scene by {result.disagreement_sigmas:.1f} sigma "
                     f"of what the scene and the pin's own sigma allow (limit {PIN_DISAGREEMENT_SIGMAS:g}): it moves "
                     f"the common focal length by {result.zoom_px - result.scene_zoom_px:+.3g} px ({pct:+.2g} %); "
                     f"{result.residual}. Check the pin's measurement ({result.description}); nothing was written")


def fit_pins(scene: SceneFit, pins: Sequence[Pin], distortion: bool, hooks: tuple[Callable, ...],
             say: Observer):
    """Each pin tested against the scene (a fit of the scene and that pin alone), then the fit of all of them.

    Returns:
        (calibration, landmarks, graph, values, one `PinResult` per pin).

    Raises:
        PinRefused: a pin disagrees with the scene (the first one found, by name).
        PinError: a pin cannot be used (e.g. its points do not triangulate).
    """
    pins = [p.retracked(scene.calib).checked(scene.calib) if isinstance(p, DistancePin) else p for p in pins]
    results, fit = [], None
    for pin in pins:
        fit = _fit(scene, [pin], PIN_ITERATIONS, hooks, say)
        try:
            result = _result(scene, pin, 0, fit, distortion)
        except RuntimeError as exc:  # GTSAM's marginals: not a disagreement (that is the test below), a failure
            raise PinError(f"pin {pin.name}: the scene and the pin leave the calibration's uncertainty indeterminate "
                           f"(GTSAM: {exc}); check the pin's measurement ({pin.describe()}); nothing was "
                           f"written") from exc
        say.log(f"self-calibration: {result.text()}")
        _refuse(result)
        results.append(result)
    if len(pins) > 1:
        fit = _fit(scene, pins, PIN_ITERATIONS, hooks, say)
    calib, points, graph, values, _ = fit
    return calib, points, graph, values, tuple(results)
