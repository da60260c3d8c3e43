"""One router per resource: detect, streams, health, model, metrics."""
