"""Benchmarks: the paper's protocol on simulated drives and the estimators side by side."""
