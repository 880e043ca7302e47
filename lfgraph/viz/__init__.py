"""Visual debugging: `RerunLogger` (an `lfgraph.Observer` writing to rerun). rerun is imported on first use."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

__all__ = ["RerunLogger", "default_blueprint"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from lfgraph.viz import rerun_log

        return getattr(rerun_log, name)
    raise AttributeError(f"module 'lfgraph.viz' has no attribute {name!r}")


if TYPE_CHECKING:
    from lfgraph.viz.rerun_log import RerunLogger, default_blueprint
