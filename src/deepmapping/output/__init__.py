"""What a run leaves behind: the run folder (poses, maps, config, metrics), pictures, exported maps."""
