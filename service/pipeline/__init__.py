"""The detect pipeline: stream store, arrival order, poses, executors, batching, live view and metrics."""
