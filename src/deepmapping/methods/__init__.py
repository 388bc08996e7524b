"""The classical registration methods (DeepMapping's baselines and warm starts): ICP in 2D and 3D,
Go-ICP, PSO, multiway and KISS-ICP odometry, loop closure, keyframe selection."""
