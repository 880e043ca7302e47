"""Trackers by name (``--tracker NAME`` on refine, check and calibrate-scene; ``tracker=`` in `RefineConfig` and
`SelfCalConfig` takes the object itself): ``chain``, the paper's chain KLT along the grid (`ChainTracker`, the
default), and ``sift``, SIFT matched between grid neighbours (`SiftTracker`: for steps too wide for KLT). Adding a
tracker is a class with ``track(images, grid) -> Tracks`` and one `register_tracker` line."""

from __future__ import annotations

from collections.abc import Callable

from lfgraph.refinement.matching import ChainTracker, Tracker
from lfgraph.refinement.unordered import SiftTracker

_TRACKERS: dict[str, Callable[[], Tracker]] = {}
DEFAULT_TRACKER = "chain"


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


register_tracker("chain", ChainTracker)
register_tracker("sift", SiftTracker)
