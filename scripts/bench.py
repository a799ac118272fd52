"""`python scripts/bench.py ...` in a checkout: the same as the installed `stablebptt bench ...`
(stablebptt/commands/bench.py)."""
import sys

from stablebptt.commands.bench import main

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
