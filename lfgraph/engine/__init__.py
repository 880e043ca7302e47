"""The one optimisation engine below every wing: the staged MAP runner (``stage_engine``), Levenberg–Marquardt
through GTSAM or with the landmarks eliminated by a vectorised Schur complement (``optimize``, ``schur``,
``schur_system``), the bulk projections (``projections``) and the noise models applied in bulk (``bulk_noise``,
``kernel_table``). No module outside this package calls an optimiser."""
