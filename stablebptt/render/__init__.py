"""Headless rendering: ``gl_backend`` (EGL or OSMesa, chosen before MuJoCo loads), ``mujoco_frames`` (frames of
a model's rollouts), ``drawing`` (a run's rollouts drawn), ``media`` (videos and pictures written atomically)."""
