"""Scripts that are not the library (run from the repository root with `python -m tools.NAME`): load and attack
harnesses, the docs' pictures and example, and the experiments whose findings the docs record (a step graph against
another, bf16 by module, decode, odometry, the server layer, stream memory, scale-out). Not installed, not in the
image."""
