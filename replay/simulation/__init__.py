"""Simulated sessions: joint trajectories, torsion, noise, rendered bi-plane images."""
