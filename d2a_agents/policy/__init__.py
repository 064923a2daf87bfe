"""Action experts: the MeanFlow policy with adaptive CFG and its baselines."""
