"""The optimiser's side of `lfgraph.viz.RerunLogger` (a mix-in): every Levenberg–Marquardt iteration live on the
``iteration`` timeline, and at the end the whole history as bar charts, one per stage name so that the legend names
the stages: ``optimizer_summary/error_decades/<stage>`` (how many decades the graph error has fallen since its stage
began, log10 of start over now, up to `MAX_DECADES`: each stage's convergence on an axis whose ticks always read 0,
1, 2, 3; the stages optimise different graphs, so their absolute errors do not compare, and a log10 of the absolute
error spanned more decades than a chart's height can label) and ``optimizer_summary/rms_px/<stage>`` (the RMS in
pixels)."""

from __future__ import annotations

import re

import numpy as np
import rerun as rr

from lfgraph.viz.blueprint import STAGE_COLOURS

MAX_DECADES = 3.0  # the error chart's bars stop here (a 1000-fold fall or more)


def _entity_part(name: str) -> str:
    """A stage name as one part of an entity path (letters, digits, ``_`` and ``-``)."""
    return re.sub(r"[^A-Za-z0-9_-]+", "_", name).strip("_") or "stage"


class OptimiserLog:
    """The optimiser history of a `lfgraph.viz.RerunLogger` (it provides ``rec`` and ``_kind``)."""

    rec: rr.RecordingStream
    _kind: str | None

    def _reset_optimiser(self) -> None:
        self.iteration_count = 0
        self._errors: list[float] = []  # graph error after every optimiser iteration
        self._start_errors: list[float] = []  # ... and before the first iteration of its stage
        self._rms_px: list[float] = []
        self._n_measurements = 0
        self._sigma_px = 1.0  # the pixel sigma of the running stage (graph errors are in its units)
        self._stages: list[tuple[int, str]] = []  # (first iteration, name) of every stage

    def set_measurements(self, n: int) -> None:
        """Number of 2-D measurements of the graph being optimised (turns the error into an RMS in pixels)."""
        self._n_measurements = int(n)

    def measurement_sigma(self, sigma_px: float) -> None:
        """The running stage's pixel sigma: its RMS is plotted in pixels, not in units of the sigma."""
        self._sigma_px = float(sigma_px)

    def _stage_starts(self, name: str) -> tuple[int, int, int]:
        """A stage named ``name`` starts with the next iteration; its colour in the charts (`stage_colour`)."""
        self._stages.append((self.iteration_count + 1, str(name)))
        return self.stage_colour(str(name))

    def stage_colour(self, name: str) -> tuple[int, int, int]:
        """The colour of a stage name's bars (and of the lines saying where it starts): one per name, in the order
        the names first appear."""
        names = list(dict.fromkeys(n for _, n in self._stages))
        k = names.index(name) if name in names else len(names)
        return STAGE_COLOURS[k % len(STAGE_COLOURS)]

    def on_iteration(self, _iteration: int, _before: float, after: float) -> None:
        """`lfgraph.engine.optimize` callback: one step on the ``iteration`` timeline per optimiser iteration."""
        first = not self._errors or any(start == self.iteration_count + 1 for start, _ in self._stages)
        self._start_errors.append(float(_before) if first else self._start_errors[-1])
        self.iteration_count += 1
        self.rec.set_time("iteration", sequence=self.iteration_count)
        self.rec.log("optimizer/error", rr.Scalars(after))
        self._errors.append(float(after))
        if self._n_measurements:
            # graph error = 0.5 sum |r / sigma|^2 (priors are negligible): RMS per point = sigma sqrt(2 e / N)
            rms = self._sigma_px * float(np.sqrt(2.0 * after / self._n_measurements))
            self.rec.log("optimizer/rms_px", rr.Scalars(rms))
            self._rms_px.append(rms)
        else:
            self._rms_px.append(float("nan"))

    def _iteration_stages(self) -> tuple[np.ndarray, list[str]]:
        """(the bar position of every iteration: one empty slot before every stage after the first, so that a
        stage's bars stand together; the stage name of every iteration)."""
        n = len(self._errors)
        first = self._kind or "all"  # iterations before any named stage (a calibration has none)
        names = []
        for i in range(1, n + 1):
            named = [name for start, name in self._stages if start <= i]
            names.append(named[-1] if named else first)
        starts = sorted({s for s, _ in self._stages if 1 < s <= n})
        iterations = np.arange(1, n + 1, dtype=np.float64)
        iterations += np.searchsorted(np.asarray(starts, dtype=np.float64), iterations, side="right")
        return iterations, names

    def optimiser_summary(self) -> None:
        """The whole optimiser history as bar charts (one bar per LM iteration, one chart per stage name, in its
        own colour: the legend names the stages), readable on any timeline."""
        if not self._errors:
            return
        iterations, names = self._iteration_stages()
        with np.errstate(divide="ignore", invalid="ignore"):
            fallen = np.log10(np.asarray(self._start_errors) / np.asarray(self._errors))
        fallen = np.clip(np.nan_to_num(fallen, nan=0.0, posinf=MAX_DECADES), 0.0, MAX_DECADES)
        rms = np.asarray(self._rms_px)
        for name in dict.fromkeys(names):
            sel = np.array([s == name for s in names])
            colour = self.stage_colour(name)
            part = _entity_part(name)
            self.rec.log(f"optimizer_summary/error_decades/{part}",
                         rr.BarChart(fallen[sel], abscissa=iterations[sel], color=colour), static=True)
            if np.isfinite(rms).any():
                self.rec.log(f"optimizer_summary/rms_px/{part}",
                             rr.BarChart(np.nan_to_num(rms[sel]), abscissa=iterations[sel], color=colour),
                             static=True)
