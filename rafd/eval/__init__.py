"""Evaluation: DOTA-style mAP and centre matching (metrics), paired bootstrap between models (compare), running a
model over a window dataset (predict), whole scans by tiles (tiled: numpy, fullscan: PyTorch) and Foxglove/MCAP logs
of an evaluation (mcap). Import the submodules; this package imports nothing (some of them need torch or shapely)."""
