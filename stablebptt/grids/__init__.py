"""Grids of runs: modes x clip modes x seeds x learning rates in one program per compile.

- ``grid``: plan and train a grid; ``pieces``: a grid split into seed ranges and merged; ``report``: its tables,
  intervals and figures.
"""
