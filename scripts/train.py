"""`python scripts/train.py ...` in a checkout: the same as the installed `stablebptt train ...`
(stablebptt/commands/train.py)."""
import sys

from stablebptt.commands.train import main

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
