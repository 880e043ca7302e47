"""The one optimisation engine below every wing: the stage schedule every wing runs its stages on (``schedule``), the
staged MAP runner (``stage_engine``), Levenberg–Marquardt through GTSAM or with the landmarks eliminated by a
vectorised Schur complement (``optimize``, ``schur``, ``schur_system``), the bulk projections (``projections``,
``board_problem``), the noise models applied in bulk (``bulk_noise``, ``kernel_table``) and the multi-view geometry
(``triangulate``). No module outside this package calls an optimiser."""
