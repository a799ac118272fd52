"""The application layer: what is built on tasks, above them in the import order.

- ``trained``: reopen a run folder or sweep cell (``open_trained`` -> ``ReopenedRun``), rebuild its task,
  roll out its policy.
- ``figures``: the pictures of the tasks without a MuJoCo scene (repulsion's paths, quantum's densities).
- ``bench``: the benchmark's options and measurements (``scripts/bench.py``).
- ``accuracy``: the accuracy studies' options (``scripts/accuracy.py``; ``stablebptt.reports.accuracy_report`` writes their
  report); each study in its own module (``trajectory_study``, ``gradient_study``, ``training_study``,
  ``contact_study``), what they share in ``measuring``.
- ``studies``: each task's side of the studies and the benchmark, reached through its registry entry
  (``Entry.studies``, found by ``study_hooks``), so no study names a task.

The layers below (tasks, grids, runs, envs, engine, physics, flows) never import these; import-linter
checks it (``[tool.importlinter]`` in pyproject.toml).
"""
