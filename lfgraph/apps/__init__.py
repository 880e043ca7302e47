"""Applications on top of the wings: synthetic captures in memory (``synth``, ``lf.synth``), studies
(``study``, ``lf.study``) and fleets (``fleet``)."""
