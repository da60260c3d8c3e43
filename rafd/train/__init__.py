"""Training: recipes, window datasets and batching, losses, the (distributed) trainer. Needs the `train` extra
(torch); import the submodules."""
