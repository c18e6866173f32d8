"""The measurement front-end: between the pipeline and every estimator, it turns samples into measurements.

:mod:`.measurements` (the maths: each measurement's value and error, pure functions on floats or arrays),
:mod:`.fixes` (fixes in the local frame), :mod:`.can` (CAN buffering and resampling), :mod:`.epochs` (GNSS period,
delay, missed epochs) and :mod:`.stream` (:class:`~sumhe.frontend.stream.FrontEnd`, the streaming estimators'
events). The batch grid (:mod:`sumhe.estimator.grid`) is the vectorised front-end of whole windows and uses the
same measurement functions.
"""
