"""What a learning curve may be drawn against and what band it draws: the plot command offers these
as its choices without importing JAX (``curves`` reads run folders, which does)."""
BANDS = ("minmax", "std")  # around the mean over seeds: min to max, or +- one standard deviation
X_AXES = ("epoch", "env-steps", "seconds", "wall-clock")
