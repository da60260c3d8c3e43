"""Synthetic Navtech radar sequences in RADIATE's exact on-disk format (numpy + opencv, torch-free)."""
from rafd.sim.api import sequence_seed, simulate_dataset, simulate_sequence
from rafd.sim.sensor import Difficulty
from rafd.sim.stats import ScanStatistics, scan_statistics

__all__ = ["Difficulty", "ScanStatistics", "scan_statistics", "sequence_seed", "simulate_dataset", "simulate_sequence"]
