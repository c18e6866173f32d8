"""Peer estimators on the same interface as sumhe's moving-horizon estimator (issue 6).

Dead reckoning, EKF, RTS smoother, UKF, particle filter and IMM, all on the shared model of
:mod:`sumhe.baseline.kinematics` and the stream contract of :mod:`sumhe.baseline.stream`; build them by name
with :func:`sumhe.estimator.registry.make_estimator`. Tuning and design: ``docs/baselines.md``.
"""
