"""One train command started from two sources of the library on one host, alternately: a change to the
start measured against its parent on the same machine and under the same load, where one start on
each of two hosts differs by as much as the change (docs/performance.md, "Tried again and not kept").

Each start is `scripts/train.py ARGS --epochs 1 --no-progress` in a fresh process, from an empty
compile cache of its own, with the source's `stablebptt` first on the path; the sources run in the
order A, B, B, A each round, so that neither always starts first. Each start's seconds to training
and its phases come from the run's own `startup.json`. `--epochs 1` ends each run after its first
epoch and evaluation; it decides no program, so the start is the one a run with `--budget` makes.

    git worktree add /tmp/parent HEAD~1      # or: mkdir /tmp/parent && git archive HEAD~1 | tar -x -C /tmp/parent
    python benchmarks/startup_pair.py --sources /tmp/parent . --out results/startup/pair -- \\
        --env WalkerStand --recipe locomotion --seeds 5

writes OUT.json (every start) and OUT.md (the starts, and each source's mean) after each start. Where
OUT.json already holds starts of the same command and sources, the order goes on after them, so that the
starts of a round can spread over several commands each held to a time limit; `--seconds S` begins no
start that the longest start of this command says would end after S seconds (the first always begins).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from stablebptt.storage import atomic_write  # noqa: E402


def start_order(rounds: int) -> list[int]:
    """The sources' indices in the order they start: A, B, B, A each round."""
    return [0, 1, 1, 0] * rounds


def start_once(source: Path, arguments: list[str], folder: Path) -> dict:
    """One start of ``scripts/train.py arguments --epochs 1`` from ``source``, in ``folder`` (its run and
    its compile cache): its ``startup.json`` entry, with the command's exit status."""
    run = folder / "run"
    environment = {**os.environ, "STABLEBPTT_COMPILE_CACHE": str(folder / "cache"),
                   "PYTHONPATH": os.pathsep.join(filter(None, [str(source), os.environ.get("PYTHONPATH", "")]))}
    command = [sys.executable, str(source / "scripts" / "train.py"), *arguments, "--epochs", "1", "--no-progress",
               "--out", str(run)]
    finished = subprocess.run(command, cwd=source, env=environment, capture_output=True, text=True)
    if finished.returncode != 0 or not (run / "startup.json").is_file():
        last = (finished.stderr.strip().splitlines() or ["(nothing on stderr)"])[-1]
        raise SystemExit(f"{source}: the command exited {finished.returncode}: {last}")
    return json.loads((run / "startup.json").read_text())[0]


def summary(starts: list[dict], names: list[str]) -> list[str]:
    """The starts as a table, in the order they ran, each phase a column; then each source's mean."""
    phases = sorted({phase for start in starts for phase in start["phases"]})
    lines = ["| start | source | s to training | " + " | ".join(phases) + " |",
             "|---:|---|---:|" + "---:|" * len(phases)]
    for number, start in enumerate(starts, 1):
        cells = [f"{start['phases'][phase]:.1f}" if phase in start["phases"] else "-" for phase in phases]
        lines.append(f"| {number} | {start['source']} | {start['seconds_to_training']:.1f} | "
                     + " | ".join(cells) + " |")
    lines.append("")
    for name in names:
        seconds = [start["seconds_to_training"] for start in starts if start["source"] == name]
        if not seconds:
            continue
        lines.append(f"- {name}: {sum(seconds) / len(seconds):.1f} s to training on average over {len(seconds)} "
                     f"starts ({', '.join(f'{value:.1f}' for value in seconds)})")
    return lines


def earlier_starts(path: Path, command: str, names: list[str]) -> list[dict]:
    """The starts a record at ``path`` already holds of this command and these sources; none where there is
    no record. A record of another command or other sources is refused rather than overwritten."""
    if not path.is_file():
        return []
    record = json.loads(path.read_text())
    if record["command"] != command or record["sources"] != names:
        raise ValueError(f"{path} records another command or other sources: give another --out")
    return record["starts"]


def write_record(out: Path, command: str, names: list[str], starts: list[dict]) -> None:
    """OUT.json (every start so far) and OUT.md (their table and each source's mean), each written whole."""
    out.parent.mkdir(parents=True, exist_ok=True)
    record = {"command": command, "sources": names, "starts": starts}
    atomic_write(out.with_suffix(".json"), json.dumps(record, indent=2).encode())
    lines = [f"# `{command}`, two sources alternately", "", *summary(starts, names)]
    atomic_write(out.with_suffix(".md"), ("\n".join(lines) + "\n").encode())


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    ours, train_arguments = (argv[:argv.index("--")], argv[argv.index("--") + 1:]) if "--" in argv else (argv, [])
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sources", nargs=2, type=Path, required=True, help="two checkouts of the library: A, B")
    parser.add_argument("--rounds", type=int, default=1, help="rounds of four starts (A, B, B, A)")
    parser.add_argument("--out", type=Path, required=True, help="OUT.json and OUT.md are written")
    parser.add_argument("--seconds", type=float, default=None,
                        help="begin no start that would end after this many seconds (the longest start so far)")
    options = parser.parse_args(ours)
    if not train_arguments:
        parser.error("give the train command's arguments after --")
    if any(argument == "--epochs" or argument.startswith("--epochs=") for argument in train_arguments):
        parser.error("each start ends after its first epoch (--epochs 1, given here): drop --epochs after --")
    sources = [source.resolve() for source in options.sources]
    for source in sources:
        if not (source / "scripts" / "train.py").is_file():
            parser.error(f"{source} is no checkout of the library: it has no scripts/train.py")
    names = [str(source) for source in options.sources]
    command = "scripts/train.py " + " ".join(train_arguments) + " --epochs 1"
    try:
        starts = earlier_starts(options.out.with_suffix(".json"), command, names)
    except ValueError as refusal:
        parser.error(str(refusal))
    began, longest = time.monotonic(), 0.0
    with tempfile.TemporaryDirectory() as scratch:
        for number, index in list(enumerate(start_order(options.rounds)))[len(starts):]:
            if longest and options.seconds is not None and time.monotonic() - began + longest > options.seconds:
                print(f"{len(starts)} of {4 * options.rounds} starts made; the same command again makes the rest", flush=True)
                break
            before = time.monotonic()
            start = start_once(sources[index], train_arguments, Path(scratch) / str(number))
            longest = max(longest, time.monotonic() - before)
            starts.append({"source": names[index], "seconds_to_training": start["seconds_to_training"],
                           "phases": start["phases"], "host": start.get("host", ""), "device": start.get("device", "")})
            print(f"{names[index]}: {start['seconds_to_training']:.1f} s to training", flush=True)
            write_record(options.out, command, names, starts)
    print("\n".join(summary(starts, names)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
