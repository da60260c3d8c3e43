"""Pictures and logs: detection and flow drawings and precision-recall plots (plots), the client's picture of a
service answer (answer) and Foxglove/MCAP logs of answers (mcap). Import the submodules; this package imports
nothing (mcap needs the `logs` extra)."""
