"""`python scripts/plot.py ...` in a checkout: the same as the installed `stablebptt plot ...`
(stablebptt/commands/plot.py)."""
import signal
import sys

if __name__ == "__main__":  # first: a Ctrl-C while the command loads ends it quietly, then in one line
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    from stablebptt.cli import stop_at_once_on_signals
    stop_at_once_on_signals()

from stablebptt.commands.plot import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
