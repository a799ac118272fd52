"""The command line: each module is one subcommand of ``stablebptt`` with a ``main(argv)``.

Installed as ``stablebptt.commands``; in a checkout each also runs as ``python scripts/NAME.py``.
"""
