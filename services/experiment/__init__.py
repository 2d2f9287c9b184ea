"""Experiments that reproduce the seed papers in simulation."""
