"""Environments in Brax's protocol (MuJoCo Playground's, a lab's own) as tasks.

- ``protocol``: Brax's environment protocol, ``load_env`` and the checks of an env; ``adapter``: ``env_task``;
  ``diagnosis``: the reward diagnosis; ``surrogate``: smooth surrogates of step rewards; ``playground``: MuJoCo
  Playground's registry.
"""
