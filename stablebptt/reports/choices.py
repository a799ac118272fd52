"""What a learning curve may be drawn against, what band it draws, and the files a figure is written as:
the commands offer these as their choices without importing JAX (``curves`` reads run folders, which does)."""
BANDS = ("minmax", "std")  # around the mean over seeds: min to max, or +- one standard deviation
X_AXES = ("epoch", "env-steps", "seconds", "wall-clock")
FORMATS = (".png", ".pdf", ".svg")  # a figure's file, by its suffix


def format_problem(path) -> str:
    """Why ``path`` cannot name a figure's file ("" where it can): its suffix says the format."""
    from pathlib import Path
    return "" if Path(path).suffix.lower() in FORMATS else f"give a file name ending in {', '.join(FORMATS)}"
