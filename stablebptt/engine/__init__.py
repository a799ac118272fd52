"""The training engine: a ``Task`` (``task``) trained by one compiled epoch, seeds vmapped into one program.

- ``training``: ``TrainConfig`` and ``make_trainer``; ``checks``: what is refused before anything compiles;
  ``memory``: the memory plan; ``program_store``: traced programs kept across processes, keyed by the code.
- ``fitting``: the epoch loop and ``train`` in memory; ``metrics``: an epoch's metrics and their rows.
"""
