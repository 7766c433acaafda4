"""End-to-end runs through the CLI: outputs written, refusing to overwrite, bad input rejected early."""

import csv
import json

import pytest

from jaxusar.cli import main

IQL_TINY = ["--set", "train.episodes=20", "--set", "train.test_every=10", "--set", "train.chunk_steps=2000",
            "--set", "env.horizon=100"]


def test_train_iql_end_to_end(tmp_path, capsys):
    out = tmp_path / "iql"
    assert main(["train", "iql", "--trials", "2", "--out", str(out)] + IQL_TINY) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["algorithm"] == "iql" and m["trials"] == 2 and len(m["episodes_to_optimal"]) == 2
    assert m["optimal_team_steps"] == 18 and m["config"]["train"]["episodes"] == 20 and m["wall_seconds"] > 0
    rows = list(csv.DictReader(open(out / "curves.csv")))
    assert sum(r["kind"] == "train" for r in rows) == 2 * 20 and sum(r["kind"] == "test" for r in rows) == 2 * 2
    assert all(int(r["steps"]) <= 100 for r in rows)
    assert (out / "params" / "trial_1.msgpack").stat().st_size > 0
    assert (out / "curves.png").read_bytes()[:4] == b"\x89PNG"
    assert "episodes 20/20" in capsys.readouterr().out  # progress was shown
    # a finished run is never overwritten without --force
    with pytest.raises(SystemExit) as e:
        main(["train", "iql", "--trials", "2", "--out", str(out)] + IQL_TINY)
    assert e.value.code == 2 and "--force" in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["train", "iql", "--set", "dqn.gamma=2"], "dqn.gamma"),
    (["train", "iql", "--set", "train.nope=1"], "train.nope"),
    (["train", "iql", "--trials", "0"], "--trials"),
    (["train", "sarsa"], "unknown algorithm"),
    (["train", "iql", "--set", "env.map=atlantis"], "unknown map"),
    (["train", "iql", "--options", "2,4"], "--options"),
    (["train", "doc", "--options", "2,x"], "--options"),
    (["train", "iql", "--config", "/nonexistent.yaml"], "does not exist"),
])
def test_train_bad_input_is_one_line_before_compiling(argv, message, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv + ["--out", str(tmp_path / "x")])
    err = capsys.readouterr().err
    assert e.value.code == 2 and message in err and "Traceback" not in err
    assert not (tmp_path / "x" / "metrics.json").exists()
