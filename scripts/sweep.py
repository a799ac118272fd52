"""`python scripts/sweep.py ...` in a checkout: the same as the installed `stablebptt sweep ...`
(stablebptt/commands/sweep.py)."""
import sys

from stablebptt.commands.sweep import main

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
