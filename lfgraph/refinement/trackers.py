"""Trackers by name (``--tracker NAME`` on refine, check and calibrate-scene; ``tracker=`` in `RefineConfig` and
`SelfCalConfig` takes the object itself): ``auto`` (`AutoTracker`, the default of refine and check: the tracker the
views' geometry calls for), ``chain``, the paper's chain KLT along the grid (`ChainTracker`; along the tree of a free
arrangement's links), and ``sift``, SIFT matched between grid neighbours or a free arrangement's links
(`SiftTracker`: for steps too wide for KLT). Adding a tracker is a class with ``track(images, grid) -> Tracks`` and
one `register_tracker` line."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from lfgraph.core.grid import ViewGrid
from lfgraph.core.grid_design import PARALLEL_DEG
from lfgraph.refinement.matching import ChainTracker, MatchSettings, Tracker, Tracks
from lfgraph.refinement.unordered import SiftTracker

_TRACKERS: dict[str, Callable[[], Tracker]] = {}
DEFAULT_TRACKER = "auto"
KLT_MAX_DEG = PARALLEL_DEG  # a free arrangement is tracked by chain KLT when its views are near-parallel as a grid's


@dataclass(frozen=True)
class AutoTracker:
    """The tracker the views' geometry calls for: on a grid (near-parallel rows and columns) the paper's chain KLT
    (`ChainTracker` with ``settings``); on a free arrangement chain KLT along the tree of its links when its steps'
    angles between optical axes, summed from the reference, stay within `KLT_MAX_DEG` in every view (near-parallel
    views: the reference's features are seen everywhere), else SIFT between the linked views (`SiftTracker`: a
    ring's views tens of degrees apart)."""

    settings: MatchSettings = field(default_factory=MatchSettings)
    sift: SiftTracker = field(default_factory=SiftTracker)

    def choose(self, grid: ViewGrid) -> Tracker:
        """The tracker for ``grid`` (see the class)."""
        if not grid.is_free:
            return ChainTracker(self.settings)
        if len(grid.link_deg) != len(grid.links):  # links given without their angles: descriptors see any angle
            return self.sift
        turned = {grid.reference: 0.0}  # along the chain, the angles of its steps summed: >= each view's from the
        for a, b in grid.chain():       # reference, whose features the chain follows into every view
            turned[b] = turned[a] + grid.link_deg[grid.links.index((min(a, b), max(a, b)))]
        return ChainTracker(self.settings) if max(turned.values()) <= KLT_MAX_DEG else self.sift

    def track(self, images: np.ndarray, grid: ViewGrid) -> Tracks:
        """Tracks of one frame's (V, H, W) uint8 views by `choose`'s tracker."""
        return self.choose(grid).track(images, grid)


def register_tracker(name: str, factory: Callable[[], Tracker]) -> None:
    """Make a tracker known by ``name`` (``factory()`` builds it with its defaults)."""
    if name in _TRACKERS:
        raise ValueError(f"a tracker named {name!r} is registered already")
    _TRACKERS[name] = factory


def tracker_names() -> tuple[str, ...]:
    """The registered trackers' names."""
    return tuple(_TRACKERS)


def tracker_by_name(name: str) -> Tracker:
    """The tracker registered as ``name``, with its defaults; ValueError naming the known ones."""
    try:
        return _TRACKERS[name]()
    except KeyError:
        raise ValueError(f"unknown tracker {name!r}: one of {', '.join(_TRACKERS)}") from None


register_tracker("auto", AutoTracker)
register_tracker("chain", ChainTracker)
register_tracker("sift", SiftTracker)
