"""The live service: sources -> time-ordered samples -> estimator -> sinks."""
