"""Learned feature weighting: the observation cache (the front end recorded once), a small
permutation-equivariant weighting module, and training through the differentiable fusion EKF."""
