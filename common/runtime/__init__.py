"""Process plumbing: Hydra entry points, progress display, memory settings."""
