"""`python scripts/plot.py ...` in a checkout: the same as the installed `stablebptt plot ...`
(stablebptt/commands/plot.py)."""
import sys

from stablebptt.commands.plot import main

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
