"""Scripts that are not the library (run from the repository root with `python -m tools.NAME`): the flood and fault
drills, the docs' pictures, tables and example, model assembly and the real fine-tune's cross-validation, a ROS 2 bag
writer. Not installed, not in the image."""
