"""Scoring a registration: ATE, point distance, rotation error (2D and 3D), evo, relation scores."""
