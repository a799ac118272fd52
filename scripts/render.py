"""`python scripts/render.py ...` in a checkout: the same as the installed `stablebptt render ...`
(stablebptt/commands/render.py)."""
import sys

from stablebptt.commands.render import main

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
