"""Graph building: GTSAM keys, noise models, the Values boundary, the parameter groups, and the graph fragments of
each wing (board observations, scene tracks, self-calibration design priors) with the one prior-table builder."""
