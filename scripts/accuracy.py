"""`python scripts/accuracy.py ...` in a checkout: the same as the installed `stablebptt accuracy ...`
(stablebptt/commands/accuracy.py)."""
import sys

from stablebptt.commands.accuracy import main

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
