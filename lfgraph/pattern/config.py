"""Options of pattern calibration."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lfgraph.factors.noise import parse_robust

METHODS = ("joint", "paper")
INITS = ("paper", "design")


@dataclass(frozen=True)
class JointSettings:
    """Options of the joint route.

    Attributes:
        robust: kernel spec, ``none`` or ``NAME[:THRESHOLD]`` (threshold in units of ``corner_sigma_px``).
        tangential: estimate p1, p2 (held at 0 otherwise, the paper's model).
        board_sigma_mm: board non-flatness tolerance; None treats the board as rigid and flat.
        corner_sigma_px: the measurement model's corner noise; sets the scale of robust thresholds and of the
            board prior's weight. Reported uncertainties are rescaled by the noise estimated from the residuals.
        max_iterations: Levenberg–Marquardt cap.
        marginals: compute 1-sigma uncertainties (costs ~0.2 s for 4x4x40).
    """

    robust: str = "none"
    tangential: bool = False
    board_sigma_mm: float | None = None
    corner_sigma_px: float = 1.0
    max_iterations: int = 100
    marginals: bool = True

    def __post_init__(self) -> None:
        parse_robust(self.robust)
        if self.board_sigma_mm is not None and not (np.isfinite(self.board_sigma_mm) and self.board_sigma_mm > 0):
            raise ValueError(f"board_sigma_mm must be positive, got {self.board_sigma_mm}")
        if not (np.isfinite(self.corner_sigma_px) and self.corner_sigma_px > 0):
            raise ValueError(f"corner_sigma_px must be positive, got {self.corner_sigma_px}")
