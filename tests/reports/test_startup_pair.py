"""Two sources started alternately on one host (benchmarks/startup_pair.py): each start a fresh process of
its source's train command, its own empty compile cache, the source's package first on the path."""
from __future__ import annotations

import importlib.util
import json
import os
from pathlib import Path

import pytest

from conftest import ROOT

_spec = importlib.util.spec_from_file_location("startup_pair", ROOT / "benchmarks" / "startup_pair.py")
startup_pair = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(startup_pair)

# A train command's stand-in: it writes the run's startup.json with the seconds its source is set to take,
# and what it was started with.
FAKE_TRAIN = '''
import json, os, sys
from pathlib import Path
out = Path(sys.argv[sys.argv.index("--out") + 1])
out.mkdir(parents=True)
seconds = float((Path(__file__).parent / "seconds").read_text())
start = {"seconds_to_training": seconds, "phases": {"compile": seconds - 10.0, "trace": 10.0},
         "host": "test", "device": "cpu"}
(out / "startup.json").write_text(json.dumps([start]))
with open(os.environ["STARTS_LOG"], "a") as log:
    log.write(json.dumps({"source": str(Path(__file__).parents[1]), "arguments": sys.argv[1:],
                          "path": os.environ["PYTHONPATH"].split(os.pathsep)[0],
                          "cache": os.environ["STABLEBPTT_COMPILE_CACHE"]}) + "\\n")
'''


def source(folder: Path, seconds: float) -> Path:
    (folder / "scripts").mkdir(parents=True)
    (folder / "scripts" / "train.py").write_text(FAKE_TRAIN)
    (folder / "scripts" / "seconds").write_text(str(seconds))
    return folder


def test_two_sources_start_alternately_each_from_its_own_cache_with_its_package_first(tmp_path, monkeypatch):
    parent, change = source(tmp_path / "parent", 90.0), source(tmp_path / "change", 80.0)
    log = tmp_path / "starts.jsonl"
    monkeypatch.setenv("STARTS_LOG", str(log))
    out = tmp_path / "record" / "pair"
    assert startup_pair.main(["--sources", str(parent), str(change), "--rounds", "2", "--out", str(out), "--",
                              "--env", "WalkerStand", "--seeds", "5"]) == 0
    starts = [json.loads(line) for line in log.read_text().splitlines()]
    assert [Path(start["source"]).name for start in starts] == ["parent", "change", "change", "parent"] * 2
    assert all(start["path"] == start["source"] for start in starts)  # its own package, not the caller's
    assert len({start["cache"] for start in starts}) == 8  # each from an empty compile cache of its own
    arguments = starts[0]["arguments"]
    assert arguments == ["--env", "WalkerStand", "--seeds", "5", "--epochs", "1", "--no-progress", "--out",
                         arguments[-1]]
    record = json.loads(out.with_suffix(".json").read_text())
    assert [start["seconds_to_training"] for start in record["starts"]] == [90.0, 80.0, 80.0, 90.0] * 2
    table = out.with_suffix(".md").read_text()
    assert f"- {parent}: 90.0 s to training on average over 4 starts" in table
    assert f"- {change}: 80.0 s to training on average over 4 starts" in table
    assert "| 2 | " + str(change) + " | 80.0 | 70.0 | 10.0 |" in table


def test_a_source_that_is_no_checkout_is_refused(tmp_path, capsys):
    with pytest.raises(SystemExit) as stopped:
        startup_pair.main(["--sources", str(tmp_path), str(tmp_path), "--out", str(tmp_path / "pair"), "--",
                           "--env", "X"])
    assert stopped.value.code == 2 and "no checkout of the library" in capsys.readouterr().err
    assert not os.path.exists(tmp_path / "pair.json")


def test_epochs_given_to_the_train_command_are_refused(tmp_path, capsys):
    with pytest.raises(SystemExit) as stopped:
        startup_pair.main(["--sources", str(tmp_path), str(tmp_path), "--out", str(tmp_path / "pair"), "--",
                           "--env", "X", "--epochs", "1"])
    assert stopped.value.code == 2 and "drop --epochs" in capsys.readouterr().err
    assert not os.path.exists(tmp_path / "pair.json")


def test_a_round_goes_on_where_a_command_held_to_a_time_limit_left_it(tmp_path, monkeypatch):
    parent, change = source(tmp_path / "parent", 90.0), source(tmp_path / "change", 80.0)
    log = tmp_path / "starts.jsonl"
    monkeypatch.setenv("STARTS_LOG", str(log))
    out = tmp_path / "pair"
    arguments = ["--sources", str(parent), str(change), "--out", str(out), "--", "--env", "WalkerStand"]
    # No time left after the first start: the second is not begun, and the record holds the first.
    assert startup_pair.main(["--seconds", "0", *arguments]) == 0
    assert [start["seconds_to_training"] for start in json.loads(out.with_suffix(".json").read_text())["starts"]] \
        == [90.0]
    assert startup_pair.main(arguments) == 0
    starts = [json.loads(line) for line in log.read_text().splitlines()]
    assert [Path(start["source"]).name for start in starts] == ["parent", "change", "change", "parent"]
    record = json.loads(out.with_suffix(".json").read_text())
    assert [start["seconds_to_training"] for start in record["starts"]] == [90.0, 80.0, 80.0, 90.0]
    # Another command's record is refused, not overwritten.
    with pytest.raises(SystemExit) as stopped:
        startup_pair.main([*arguments, "--seeds", "5"])
    assert stopped.value.code == 2
    assert len(json.loads(out.with_suffix(".json").read_text())["starts"]) == 4
