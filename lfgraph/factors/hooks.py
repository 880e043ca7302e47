"""User factors: a documented hook through which a script adds its own factors or priors to lfgraph's graphs.

Give ``graph_hooks=(fn, ...)`` in `lfgraph.CalibrateConfig` or `lfgraph.RefineConfig`; each ``fn(ctx)`` is called
with a `GraphContext` after lfgraph has built a graph and before it is optimised. Add factors to ``ctx.graph``
(keys from `lfgraph.factors.keys`; ``ctx.initial.exists(key)`` says whether a variable is in this graph). Values
must not be inserted for keys lfgraph does not use unless you also add factors on them.

    def hold_view_3(ctx):
        if ctx.initial.exists(view_pose_key(3)):
            ctx.graph.add(gtsam.PriorFactorPose3(view_pose_key(3), ctx.initial.atPose3(view_pose_key(3)),
                                                 pose_noise(1e-4, 1e-5)))
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import gtsam

from lfgraph.core.calibration import Calibration


@dataclass(frozen=True)
class GraphContext:
    """What a graph hook receives.

    Attributes:
        kind: ``"calibration"`` (the joint pattern graph) or ``"refinement"``.
        stage: the refinement stage name (``points``, ``poses``, ...); None for calibration.
        graph: the factor graph, to add to.
        initial: the initial values (the variables of this graph).
        num_views: views of the array; view v's pose is ``view_pose_key(v)`` and intrinsics ``calib_key(v)``.
        calib: the calibration the graph starts from (None for calibration, where it is being estimated).
    """

    kind: str
    stage: str | None
    graph: gtsam.NonlinearFactorGraph
    initial: gtsam.Values
    num_views: int
    calib: Calibration | None = None


GraphHook = Callable[[GraphContext], None]


def as_hooks(hooks: GraphHook | Iterable[GraphHook] | None, what: str) -> tuple[GraphHook, ...]:
    """``graph_hooks`` as given to a config — one function, several, or None — as a tuple of functions.

    Raises:
        TypeError: something that is not a function (``what`` names the setting).
    """
    if hooks is None:
        return ()
    if callable(hooks):
        return (hooks,)
    try:
        out = tuple(hooks)
    except TypeError:
        raise TypeError(f"{what} must be a function taking a GraphContext, or a sequence of them; got "
                        f"{type(hooks).__name__}") from None
    for hook in out:
        if not callable(hook):
            raise TypeError(f"{what} must hold functions taking a GraphContext, got {hook!r}")
    return out


def run_hooks(hooks: Iterable[GraphHook], ctx: GraphContext) -> None:
    """Call each hook; an exception names the hook that raised it."""
    for hook in hooks:
        try:
            hook(ctx)
        except Exception as exc:
            name = getattr(hook, "__name__", repr(hook))
            raise RuntimeError(f"graph hook {name} failed on the {ctx.kind} graph"
                               f"{'' if ctx.stage is None else f' (stage {ctx.stage})'}: {exc}") from exc
