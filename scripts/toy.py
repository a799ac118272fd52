"""`python scripts/toy.py ...` in a checkout: the same as the installed `stablebptt toy ...`
(stablebptt/commands/toy.py)."""
import sys

from stablebptt.commands.toy import main

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
