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


def test_train_hierarchical_end_to_end(tmp_path):
    out = tmp_path / "hier"
    assert main(["train", "hierarchical", "--trials", "1", "--out", str(out), "--quiet",
                 "--set", "train.episodes=20", "--set", "train.chunk_steps=1000", "--set", "env.horizon=60",
                 "--set", "hierarchical.coordinator.episodes=3", "--set", "hierarchical.coordinator.chunk_steps=16"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["options"] == ["NAVIGATE-TO-TOP-ROOM", "NAVIGATE-TO-BOTTOM-ROOM", "TRIAGE-TOP-VICTIM",
                            "TRIAGE-BOTTOM-VICTIM"]
    assert len(m["tasks"]) == 6 and set(m["subpolicy_episodes_to_optimal"]["per_task"]) == set(m["tasks"])
    for k in ("episodes_to_optimal", "coordinator_episodes_to_optimal", "seconds", "wall_seconds"):
        assert k in m
    # the total is the sub-policy sum plus the coordinator's count, when both exist
    s, c, t = (m["subpolicy_episodes_to_optimal"]["sum"][0], m["coordinator_episodes_to_optimal"][0],
               m["episodes_to_optimal"][0])
    assert t == (None if s is None or c is None else s + c)
    for f in ("fig4_subpolicies.png", "fig4_agent0_navigate-to-bottom-room.png", "fig4_triage-top-victim.png",
              "coordinator.png", "team_episode.png", "curves.csv", "params/trial_0.msgpack"):
        assert (out / f).stat().st_size > 0, f
    stages = {r["stage"] for r in csv.DictReader(open(out / "curves.csv"))}
    assert stages == {"subpolicy", "coordinator"}
