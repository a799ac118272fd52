"""The cart-pole MJCF files, shipped as package data (installed as ``stablebptt.models``).

``stablebptt/models/README.md`` documents the MJCF task convention these files follow.
"""
from importlib.resources import files
from pathlib import Path

DIRECTORY = Path(str(files(__name__)))


def cartpole(poles: int) -> Path:
    """The MJCF file of the cart-pole with ``poles`` poles."""
    return DIRECTORY / f"cartpole_{poles}.xml"
