"""Environments in Brax's protocol (MuJoCo Playground's, a lab's own) as tasks.

- ``adapter``: ``env_task`` and ``load_env``, the reward diagnosis; ``playground``: MuJoCo Playground's registry.
"""
