"""One vocabulary for every judgement lfgraph gives: a view's (refine, check), a check's and a fleet camera's."""

from __future__ import annotations

from enum import StrEnum


class Verdict(StrEnum):
    """A verdict; compares equal to (and prints as) its name, so JSON, CSV and text carry the plain word.

    A view (refine, check): OK, DRIFTED, UNCERTAIN or REFERENCE. A check of a whole capture: OK, DRIFTED, UNCERTAIN
    or MISMATCH. A fleet camera: OK, DRIFTED, UNCERTAIN or ERROR.
    """

    OK = "OK"  # no significant change that matters (a view), no view drifted and at least one confirmed (a check)
    DRIFTED = "DRIFTED"  # a change that is significant, above the tolerance and confirmed by held-out tracks
    UNCERTAIN = "UNCERTAIN"  # the data cannot tell
    REFERENCE = "REFERENCE"  # the reference view: the gauge, never judged
    MISMATCH = "MISMATCH"  # the calibration does not fit this camera (other intrinsics explain the tracks far better)
    ERROR = "ERROR"  # the work failed (a fleet row, with the error)

    def __repr__(self) -> str:  # a dict of counts prints as {'OK': 3, ...}, as it did when verdicts were strings
        return repr(self.value)
