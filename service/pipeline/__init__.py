"""The detect pipeline: stream store, arrival order, poses, executors, live view and metrics."""
