"""Synthetic Navtech radar sequences in RADIATE's exact on-disk format (numpy + opencv, torch-free)."""

from rafd.sim.api import sequence_seed, simulate_dataset, simulate_sequence
from rafd.sim.sensor import Conditions, Difficulty

__all__ = ["Conditions", "Difficulty", "sequence_seed", "simulate_dataset", "simulate_sequence"]
