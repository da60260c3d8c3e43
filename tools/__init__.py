"""Scripts that are not the library (run from the repository root with `python -m tools.NAME`): load and attack
harnesses, the scale-out benchmark, the README example writer. Not installed, not in the image."""
