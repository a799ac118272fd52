"""The command line: each module is one subcommand of ``stablebptt`` with a ``main(argv)``.

In a checkout each also runs as ``python scripts/NAME.py``. Every command runs in a process of its
own, so the package sets the process's XLA:CPU threads and how often Python collects its garbage
here, before any command computes (``stablebptt.runtime.one_cpu_thread`` and
``rarer_garbage_collections`` say why); a library user's process is left as it is.
"""
from stablebptt.runtime import one_cpu_thread, rarer_garbage_collections

one_cpu_thread()
rarer_garbage_collections()
