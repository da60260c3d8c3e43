"""Measuring: timing and percentiles, starting a service process on loopback, HTTP load, FLOP counts and the
machine's matmul peaks (torch-free but for `flops`), and the synthetic accuracy benchmark (`accuracy`, `variants`)
and training-speed benchmark (`training`). The commands (`rafd bench speed | accuracy | training | capacity`) and
the scripts in `tools/` build on these.
Import the submodules."""
