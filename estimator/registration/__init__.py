"""Rigid 3D-3D registration: the registry, the swarm estimators, the baselines, refinement."""
