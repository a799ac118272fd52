"""Each built-in task's side of the studies and the benchmark: ``cartpole`` (the MJCF task's cart-poles),
``repulsion`` and ``quantum``. A task's registry entry names its module; ``stablebptt.apps.study_hooks``
says what such a module may define and finds it."""
