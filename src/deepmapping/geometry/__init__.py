"""Rigid-motion maths: SE(2), SE(3), closed-form alignment, distance fields, normals (numpy/scipy only)."""
