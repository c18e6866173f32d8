"""Estimators: the state-uniform (SU) batch and moving-horizon estimators."""
