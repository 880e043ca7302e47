"""Levenberg–Marquardt on GTSAM factors with the landmarks eliminated by a vectorised Schur complement.

A refinement graph has thousands of landmarks, each seen by every view: GTSAM's multifrontal elimination builds a
dense (3 + 6 V)^2 Hessian per landmark (a 5x5 grid: 153^2 doubles, ~0.1 ms each), so a linear solve costs ~0.1 ms per
landmark. Here the factors stay GTSAM's (C++ linearisation, noise models and robust kernels baked into the whitened
Jacobian, user hooks' factors included); only the linear solve differs: the whitened sparse Jacobian
(``sparseJacobian_``) is reduced to the camera block in numpy (`lfgraph.engine.schur_system`: 3x3 landmark blocks
inverted in one batch, one GEMM for the Schur complement), solved densely, and the landmarks back-substituted.

The loop follows GTSAM's `LevenbergMarquardtOptimizer` (``lambdaInitial`` 1e-5, factor 10, upper bound 1e5, damping
``lambda I``, a step accepted when the model fidelity exceeds 1e-3, the same relative/absolute decrease tests), so it
converges to the same minimum. ``marginal_covariance`` gives the camera-block marginals as GTSAM's `Marginals` would
(the inverse of the reduced camera system at the solution).

A graph it cannot reduce (a row touching two landmarks, a key the values do not hold) raises `NotReducible`: the
caller then falls back to GTSAM's own optimiser. `lfgraph.engine.projections.ProjectionProblem` is the same LM
on the refinement's projections evaluated in bulk (no GTSAM factor per observation).
"""

from __future__ import annotations

import time

import gtsam
import numpy as np

from lfgraph.core.parallel import one_blas_thread
from lfgraph.engine.result import OptimizationResult
from lfgraph.engine.schur_system import (
    NotReducible,
    ReducedSystem,
    SchurLayout,
    camera_block,
    chol3_inv,
    full_step,
    inv3,
    landmark_blocks,
    reduced_system,
    schur_layout,
    vector_values,
)

LAMBDA_INITIAL = 1e-5  # GTSAM's LevenbergMarquardtParams defaults
LAMBDA_FACTOR = 10.0
LAMBDA_UPPER = 1e5
MIN_MODEL_FIDELITY = 1e-3
TINY_LINEAR_CHANGE = 1e-20  # a predicted cost decrease below this is treated as none (fidelity by the sign alone)


def _solve(sys_: ReducedSystem, lam: float) -> tuple[np.ndarray, np.ndarray]:
    """(landmark step (N,3), camera step (C,)) of the damped normal equations; raises LinAlgError when singular.

    Each landmark block is factored ``V = L L^T`` (closed form); with cameras, ``Y = L^-1 W`` and the reduced camera
    system ``S = H - Y^T Y`` is formed by a symmetric rank-k update (half a general product's work)."""
    n_lm, n_c, d = sys_.V.shape[0], sys_.H.shape[0], sys_.V.shape[-1]
    linv = chol3_inv(sys_.V + lam * np.eye(3)) if d == 3 else _chol_inv(sys_.V + lam * np.eye(d))
    u = np.matmul(linv, sys_.g_l[..., None]).reshape(-1)  # L^-1 g_l
    dc = np.zeros(n_c)
    if n_c:
        Y = _times_w(linv, sys_.W).reshape(-1, n_c)  # noqa: N806  (3N, C)
        Ls = np.linalg.cholesky(sys_.H + lam * np.eye(n_c) - Y.T @ Y)  # noqa: N806  (numpy calls syrk for Y^T Y)
        dc = np.linalg.solve(Ls.T, np.linalg.solve(Ls, sys_.g_c - Y.T @ u))
        u = u - Y @ dc
    return np.matmul(np.swapaxes(linv, 1, 2), u.reshape(n_lm, d, 1))[..., 0], dc  # dl = L^-T (L^-1 g_l - Y dc)


def _chol_inv(V: np.ndarray) -> np.ndarray:  # noqa: N803
    """`chol3_inv` for blocks of any size (a calibration's 6x6 board poses): batched Cholesky and inverse."""
    return np.linalg.inv(np.linalg.cholesky(V))  # raises LinAlgError for a block that is not positive definite


def _times_w(vinv: np.ndarray, W: np.ndarray) -> np.ndarray:  # noqa: N803
    """Batched (N, 3, 3) @ (N, 3, C) (np.matmul: ~10x faster than einsum or broadcasting at these sizes)."""
    return np.matmul(vinv, W)


class GraphProblem:
    """A GTSAM graph whose landmarks (keys of ``landmark_char``, 3-D) are eliminated; state: `gtsam.Values`.

    ``landmark_iterations`` > 0: after every step the landmarks are solved again with the cameras held, by this many
    Gauss–Newton iterations of their own 3x3 blocks ("embedded point iterations", variable projection: Hong, Zach and
    Fitzgibbon, CVPR 2017). A step of the cameras along a valley that every landmark must follow nonlinearly (a
    common zoom moves every depth, the hidden principal-point gauge every inverse depth) then keeps its full length:
    measured on a 4x4 self-calibration, 4-8 iterations to the minimum where plain Levenberg–Marquardt took 150 and
    more, each ~0.96 of the last's decrease. A landmark iteration that raises the graph's error is undone (and ends
    the iterations), so the step LM judges is never worse than its plain one; a landmark whose block is not positive
    definite stays where the step put it.
    """

    def __init__(self, graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, landmark_char: str,
                 landmark_iterations: int = 0):
        self.graph, self.initial = graph, initial
        self.layout = schur_layout(initial, landmark_char)
        self.landmark_iterations = int(landmark_iterations)
        self._known: tuple[gtsam.Values, float] | None = None  # the last re-solved state and its error

    def error(self, state: gtsam.Values) -> float:
        """GTSAM's graph error at ``state`` (for the state the last `retract` re-solved, the error it found)."""
        if self._known is not None and self._known[0] is state:
            return self._known[1]
        return float(self.graph.error(state))

    def system(self, state: gtsam.Values) -> ReducedSystem:
        """The undamped normal equations of the graph linearised at ``state`` (`ReducedSystem`: 3x3 landmark blocks)."""
        return reduced_system(self.graph.linearize(state), self.layout)

    def retract(self, state: gtsam.Values, dl: np.ndarray, dc: np.ndarray) -> gtsam.Values:
        """``state`` moved by a landmark step ``dl`` (N, 3) and a camera step ``dc`` (C,); with ``landmark_iterations``
        the landmarks are then solved again with the cameras held (see the class docstring)."""
        state = state.retract(vector_values(self.layout, full_step(self.layout, dl, dc)))
        if not self.landmark_iterations or not self.layout.n_landmarks:
            return state
        no_camera_step = np.zeros(self.layout.n_camera)
        error = self.error(state)
        for _ in range(self.landmark_iterations):
            V, g_l = landmark_blocks(self.graph.linearize(state), self.layout)[-2:]  # noqa: N806
            step = np.matmul(inv3(V, strict=False), g_l[..., None])[..., 0]
            moved = state.retract(vector_values(self.layout, full_step(self.layout, step, no_camera_step)))
            moved_error = self.error(moved)
            if not moved_error <= error:  # Gauss–Newton overshot (or NaN): keep the landmarks as they were
                break
            state, error = moved, moved_error
        self._known = (state, error)  # the LM loop asks for it next
        return state


def _linear_change(s: ReducedSystem, dl: np.ndarray, dc: np.ndarray) -> float:
    """Decrease of the linearised cost for the step: 0.5 |b|^2 - 0.5 |A d - b|^2 = d.g - 0.5 d.H.d."""
    dg = float(np.sum(dl * s.g_l) + dc @ s.g_c)
    vdl = np.matmul(s.V, dl[..., None])[..., 0] if dl.size else dl
    dhd = float(np.sum(dl * vdl) + dc @ s.H @ dc)
    if dl.size and dc.size:
        dhd += 2.0 * float(dl.ravel() @ (s.W.reshape(-1, len(dc)) @ dc))
    return dg - 0.5 * dhd


def _left_to_gain(history: list[float]) -> float:
    """The cost decrease still to come if the last two decreases keep shrinking by their ratio (Aitken's estimate of
    a linearly converging sequence's limit; inf unless they shrink). A robust (reweighted) problem also stops once
    that is below its relative tolerance: on the kernel table (`benchmarks/refine.py --kernels-only`) 10-33 % fewer
    iterations for Huber, Cauchy, Tukey and Geman-McClure at 3.787 sigma, every transfer at infinity within 0.001 px
    of the stop on the last decrease alone (Geman-McClure at 1 sigma, whose decreases shrink by only ~0.75 per
    iteration, is left to that stop)."""
    if len(history) < 3:
        return float("inf")
    last, before = history[-2] - history[-1], history[-3] - history[-2]
    if not 0 <= last < before:
        return float("inf")
    ratio = last / before
    return last * ratio / (1.0 - ratio)


EXTRAPOLATE_MIN = 1.5  # an accepted step is stretched when the cost's parabola along it puts the minimum beyond
EXTRAPOLATE_MAX = 8.0  # this multiple of the step (and by at most this one)


def _extrapolate(problem, state, error: float, sys_: ReducedSystem, dl: np.ndarray, dc: np.ndarray, cand,
                 cand_error: float):
    """An accepted step stretched to the minimum of the parabola through the cost at 0 and at the step with the
    gradient's slope at 0, when that lies beyond `EXTRAPOLATE_MIN` steps and the stretched step costs less (one
    more cost evaluation). When the stretch costs more than the step, the parabola through the slope and the cost
    at the stretch gives a shorter one (at most half the stretch, one more evaluation): on the kernel table's
    Geman-McClure at 1 sigma 8 % fewer iterations. For a problem that sets ``extrapolate``: a robust model's
    reweighted steps fall short where its kernel flattens (the weights are held through a step), so a robust stage
    converges linearly; the minimum is unchanged."""
    slope = -float(np.sum(dl * sys_.g_l) + dc @ sys_.g_c)  # d cost / d alpha at 0 (negative: a descent step)
    curvature = cand_error - error - slope
    if slope >= 0 or curvature <= 0:
        return cand, cand_error
    alpha = -slope / (2.0 * curvature)
    if alpha < EXTRAPOLATE_MIN:
        return cand, cand_error
    a = min(alpha, EXTRAPOLATE_MAX)
    far = problem.retract(state, a * dl, a * dc)
    far_error = problem.error(far)
    if far_error < cand_error:
        return far, far_error
    # the parabola overshot: back to the minimum of the one through the slope at 0 and the cost found there
    curvature = (far_error - error - slope * a) / (a * a)
    back = min(-slope / (2.0 * curvature), 0.5 * a) if curvature > 0 else 0.0
    if back < EXTRAPOLATE_MIN:
        return cand, cand_error
    mid = problem.retract(state, back * dl, back * dc)
    mid_error = problem.error(mid)
    return (mid, mid_error) if mid_error < cand_error else (cand, cand_error)


def optimize_schur(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, landmark_char: str,
                   max_iterations: int = 100, relative_error_tol: float = 1e-10, absolute_error_tol: float = 1e-12,
                   error_tol: float = 0.0, callback=None, landmark_iterations: int = 0) -> OptimizationResult:
    """Levenberg–Marquardt as GTSAM runs it, the linear solves by the Schur complement on landmarks
    (``landmark_iterations``: embedded point iterations after every step, see `GraphProblem`).

    Raises:
        NotReducible: the graph cannot be reduced (the caller falls back to GTSAM).
    """
    return optimize_problem(GraphProblem(graph, initial, landmark_char, landmark_iterations), initial, max_iterations,
                            relative_error_tol, absolute_error_tol, error_tol, callback)


def optimize_problem(problem, state, max_iterations: int = 100, relative_error_tol: float = 1e-10,
                     absolute_error_tol: float = 1e-12, error_tol: float = 0.0,
                     callback=None) -> OptimizationResult:
    """The Levenberg–Marquardt loop over a problem (``error``, ``system``, ``retract``); ``values`` of the result
    is the final state (a `ProjectionProblem`'s: (values, points)).
    """
    with one_blas_thread():
        return _optimize(problem, state, max_iterations, relative_error_tol, absolute_error_tol, error_tol, callback)


def _optimize(problem, state, max_iterations, relative_error_tol, absolute_error_tol, error_tol,
              callback) -> OptimizationResult:
    start = time.perf_counter()
    error = problem.error(state)
    initial_error = error
    history = [error]
    lam = LAMBDA_INITIAL
    iterations = 0
    converged = False
    predict = getattr(problem, "extrapolate", False)  # a robust problem: reweighting converges linearly
    # its stop is relative to the cost, or to what Gaussian noise would cost (`noise_cost`) when that is more
    noise_cost = float(getattr(problem, "noise_cost", 0.0)) if predict else 0.0
    while iterations < max_iterations:
        if error <= error_tol:
            converged = True
            break
        sys_ = problem.system(state)
        accepted = False
        new_state, new_error = state, error
        while True:
            try:
                dl, dc = _solve(sys_, lam)
                ok = bool(np.all(np.isfinite(dl)) and np.all(np.isfinite(dc)))
            except np.linalg.LinAlgError:
                ok = False
            if ok:
                linear_change = _linear_change(sys_, dl, dc)
                if linear_change >= 0:
                    cand = problem.retract(state, dl, dc)
                    cand_error = problem.error(cand)
                    change = error - cand_error
                    tiny = linear_change <= TINY_LINEAR_CHANGE
                    fidelity = (1.0 if change >= 0 else -1.0) if tiny else change / linear_change
                    if np.isfinite(cand_error) and fidelity > MIN_MODEL_FIDELITY:
                        if getattr(problem, "extrapolate", False):
                            cand, cand_error = _extrapolate(problem, state, error, sys_, dl, dc, cand, cand_error)
                        new_state, new_error, accepted = cand, cand_error, True
                        lam = lam / LAMBDA_FACTOR
                        break
            lam *= LAMBDA_FACTOR
            if lam >= LAMBDA_UPPER:
                break
        iterations += 1
        if not accepted:  # GTSAM: "cannot decrease error with maximum lambda": stop where we are
            converged = True
            break
        if callback is not None:
            callback(iterations, error, new_error)
        history.append(new_error)
        decrease = error - new_error
        state, previous, error = new_state, error, new_error
        scale, now = max(previous, noise_cost), max(error, noise_cost)
        if decrease <= absolute_error_tol or (scale > 0 and decrease / scale <= relative_error_tol) \
                or error <= error_tol or (predict and _left_to_gain(history) <= relative_error_tol * now):
            converged = True
            break
    return OptimizationResult(state, initial_error, error, iterations, converged or iterations < max_iterations,
                              time.perf_counter() - start, tuple(history))


PSEUDO_INVERSE_RCOND = 1e-10  # landmark-block eigenvalues below this fraction of the largest carry no information


def marginal_covariance(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                        landmark_char: str) -> tuple[np.ndarray, SchurLayout]:
    """The (C, C) joint marginal covariance of every non-landmark variable at ``values`` (the inverse of the
    reduced camera system, as GTSAM's `Marginals`), with the layout to find each key's block (`camera_block`).

    Raises:
        NotReducible, numpy.linalg.LinAlgError (indeterminate).
    """
    problem = GraphProblem(graph, values, landmark_char)
    return problem_covariance(problem, values), problem.layout


def problem_covariance(problem, state) -> np.ndarray:
    """The (C, C) marginal covariance of the camera variables of a problem at ``state``."""
    with one_blas_thread():
        sys_ = problem.system(state)
        n_c = sys_.H.shape[0]
        S = sys_.H.copy()  # noqa: N806
        if sys_.V.shape[0] and sys_.V.shape[-1] != 3:  # e.g. board poses (6x6): positive definite, or raise
            S -= sys_.W.reshape(-1, n_c).T @ _times_w(np.linalg.inv(sys_.V), sys_.W).reshape(-1, n_c)
        elif sys_.V.shape[0]:
            inv = inv3(sys_.V, strict=False)
            # a landmark block singular in floating point (a far landmark on a short baseline: its depth direction
            # carries ~no information, and its Jacobian none either) is marginalised by its pseudo-inverse; so is
            # one whose determinant came out a rounding error above zero (a track of two views captured at one
            # place, templeSparseRing's 0 and 10: an eigenvalue ratio of -4e-16 to 1e-16, whose inverse of ~1e16
            # left the reduced system indefinite)
            ev = np.linalg.eigvalsh(sys_.V)
            flat = (ev[:, 0] <= PSEUDO_INVERSE_RCOND * ev[:, -1]) & (ev[:, -1] > 0.0)
            if flat.any():
                inv[flat] = np.linalg.pinv(sys_.V[flat], rcond=PSEUDO_INVERSE_RCOND, hermitian=True)
            vw = _times_w(inv, sys_.W).reshape(-1, n_c)
            S -= sys_.W.reshape(-1, n_c).T @ vw
        Ls = np.linalg.cholesky(S)  # noqa: N806  (raises when indeterminate)
        inv_l = np.linalg.solve(Ls, np.eye(n_c))
        return inv_l.T @ inv_l


class CameraMarginals:
    """The marginal covariances of camera variables (poses, intrinsics), the one posterior path of refine, check and
    calibrate-scene: the inverse of the reduced camera system — of a bulk ``problem`` at ``state`` (its projections
    as the fit ran them) or of a GTSAM ``graph`` at ``values`` — and GTSAM's own `Marginals` of the graph where the
    reduction cannot (a factor it does not reduce, a system singular in floating point: GTSAM eliminates with
    pivoting). ``build`` makes that graph and its values only when needed (a bulk problem has none).

    Raises:
        RuntimeError: GTSAM's `Marginals` failed too (an undetermined parameter), or no graph to fall back on.
    """

    def __init__(self, graph: gtsam.NonlinearFactorGraph | None = None, values: gtsam.Values | None = None,
                 landmark_char: str = "l", problem=None, state=None, build=None):
        self._cov = self._layout = self._marginals = None
        try:
            if problem is not None:
                self._cov, self._layout = problem_covariance(problem, state), problem.layout
            elif graph is not None:
                self._cov, self._layout = marginal_covariance(graph, values, landmark_char)
        except (NotReducible, np.linalg.LinAlgError):
            self._cov = None
        if self._cov is None:
            if graph is None and build is not None:
                graph, values = build()
            if graph is None:
                raise RuntimeError("the reduced system is indeterminate and there is no graph to fall back on")
            self._marginals = gtsam.Marginals(graph, values)  # (callers silence GTSAM's prints: gtsam_quiet)

    def block(self, a: int, b: int | None = None) -> np.ndarray:
        """The covariance block of keys ``a`` and ``b`` (``b`` None: ``a``'s own marginal), tangent order."""
        b = a if b is None else b
        if self._cov is not None:
            return self._cov[camera_block(self._layout, a), camera_block(self._layout, b)]
        if a == b:
            return np.asarray(self._marginals.marginalCovariance(a))
        return np.asarray(self._marginals.jointMarginalCovariance(gtsam.KeyVector([a, b])).at(a, b))

    def joint(self, keys: list[int]) -> np.ndarray:
        """The joint covariance of ``keys``, blocks in that order."""
        if self._cov is not None:
            idx = np.concatenate([np.arange(s.start, s.stop) for s in (camera_block(self._layout, k) for k in keys)])
            return self._cov[np.ix_(idx, idx)]
        return np.asarray(self._marginals.jointMarginalCovariance(gtsam.KeyVector(keys)).fullMatrix())
