"""Run folders: what one run keeps, so that it resumes exactly and renders later.

- ``run_folder``: config, metrics, parameters and checkpoints, each written atomically; the lock on a folder.
- ``model_store``: an MJCF run's model as given and as compiled, a grid's shared copies.
- ``epochs``: a trainer's epochs into a folder, checkpointed as they go.
- ``session``: a run begun or resumed as ``stablebptt train`` does (``begin``): the task and its trainer
  built, the folder claimed once the task has settled, the state to train from.
"""
