"""Issue 39 item 3: ``liris eval`` builds one frozen request and hands it to one small mode.

The numbers of each mode are pinned by the tests of that mode (test_eval_cli,
test_sessions_cli, test_pairs, test_eval_many, test_external_loops); these
tests pin the parse (options -> request), the choice of mode, and that each
mode refuses the options it does not use before reading any file.
"""

from __future__ import annotations

import dataclasses
import inspect
from pathlib import Path

import pytest

from lidar_iris_eval.cli import eval_cmd
from lidar_iris_eval.cli.eval_many import run_many
from lidar_iris_eval.cli.eval_request import EvalRequest
from lidar_iris_eval.cli.loops_eval import run_loops
from lidar_iris_eval.cli.pairs_eval import run_pairs
from lidar_iris_eval.cli.sequence_eval import run_sequence
from lidar_iris_eval.cli.sessions_eval import run_sessions
from lidar_iris_eval.cli.sessions_plan import run_sessions_plan
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.settings import Settings

CONV = Settings()


def _request(**fields) -> EvalRequest:
    return EvalRequest(convention=CONV, settings=CONV, **fields)


def test_request_is_frozen_and_checks_workers():
    req = _request(sequences=(Path("s"),), protocols=("1",))
    with pytest.raises(dataclasses.FrozenInstanceError):
        req.workers = 4  # type: ignore[misc]
    with pytest.raises(LirisError, match="--workers 0"):
        _request(workers=0)


@pytest.mark.parametrize("fields, mode", [
    ({"sequences": (Path("a"),)}, "sequence"),
    ({"sequences": (Path("a"), Path("b"))}, "many"),
    ({"sequences": ()}, "many"),                                 # refused by run_many
    ({"sequences": (Path("a"),), "pairs_text": "ssc"}, "pairs"),
    ({"sequences": (Path("a"), Path("b")), "pairs_text": "ssc"}, "many"),
    ({"sequences": (Path("a"),), "loop_paths": (Path("l.g2o"),)}, "loops"),
    ({"loop_paths": (Path("l.g2o"),)}, "loops"),                 # --poses alone
    ({"query": Path("q"), "database": Path("d")}, "sessions"),
    ({"align": Path("T.txt")}, "sessions"),                      # refused by run_sessions
    ({"query": Path("q"), "sequences": (Path("a"),)}, "sessions"),
])
def test_mode_follows_the_options_precedence(fields, mode):
    assert eval_cmd.mode_of(_request(**fields)) == mode


def test_a_plan_of_sessions_and_a_plan_of_sequences(tmp_path):
    sessions = tmp_path / "s.yaml"
    sessions.write_text("descriptors: m2dp\nsessions: [a, b]\n")
    sequences = tmp_path / "q.yaml"
    sequences.write_text("descriptors: m2dp\nsequences: [a, b]\n")
    assert eval_cmd.mode_of(_request(plan=sessions)) == "sessions-plan"
    assert eval_cmd.mode_of(_request(plan=sequences)) == "many"
    # with a SEQUENCE the plan is not read as sessions: run_many refuses both
    assert eval_cmd.mode_of(_request(plan=sessions, sequences=(Path("a"),))) == "many"


def test_every_mode_takes_the_request_alone():
    for run in (run_sequence, run_many, run_sessions, run_sessions_plan, run_pairs, run_loops):
        assert list(inspect.signature(run).parameters) == ["req"], run.__name__
    assert set(eval_cmd.MODE_RUNNERS) == {"sequence", "many", "sessions", "sessions-plan",
                                          "pairs", "loops"}


@pytest.mark.parametrize("run, fields, flag", [
    (run_sessions, {"query": Path("q"), "database": Path("d"), "protocols": ("1",)},
     "--protocol"),
    (run_sessions, {"query": Path("q"), "database": Path("d"), "odometry": "kiss-icp"},
     "--odometry kiss-icp"),
    (run_sessions, {"query": Path("q")}, "--query/--database"),
    (run_sessions, {"query": Path("q"), "database": Path("d"),
                    "export_path": Path("x.g2o")}, "--export-loops"),
    (run_sessions, {"query": Path("q"), "database": Path("d"), "convention_band": True},
     "--convention-band"),
    (run_sessions_plan, {"plan": Path("p.yaml"), "protocols": ("2",)}, "--protocol"),
    (run_pairs, {"sequences": (Path("a"),), "pairs_text": "ssc", "protocols": ("1",)},
     "--protocol"),
    (run_pairs, {"sequences": (Path("a"),), "pairs_text": "ssc", "convention_band": True},
     "--convention-band"),
    (run_many, {"sequences": (Path("a"), Path("b")), "seeds": (1, 2)},
     "--refine/--gt-pose/--odometry/--seeds"),
    (run_many, {"sequences": (Path("a"), Path("b")), "as_json": True},
     "--export-loops/--json"),
    (run_many, {"sequences": (Path("a"),), "plan": Path("p.yaml")}, "--plan"),
    (run_many, {"sequences": (Path("a"), Path("b")), "pairs_text": "ssc"}, "--pairs/--ranking"),
    (run_many, {"sequences": (Path("a"), Path("b")), "ranking": True}, "--pairs/--ranking"),
    (run_loops, {"sequences": (Path("a"), Path("b")), "loop_paths": (Path("l.g2o"),)},
     "--loops"),
    (run_loops, {"loop_paths": (Path("l.g2o"),), "protocols": ("2",)}, "--protocol"),
    (run_loops, {"loop_paths": (Path("l.g2o"),), "descriptor_text": "m2dp"}, "--loops"),
    (run_sequence, {"sequences": (Path("a"),), "seeds": (1,), "convention_band": True},
     "--convention-band"),
])
def test_each_mode_refuses_what_it_does_not_use(run, fields, flag, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # none of these paths exists: refused before any is read
    with pytest.raises(LirisError) as err:
        run(_request(**fields))
    assert str(err.value).startswith(flag), str(err.value)
    assert not any(tmp_path.iterdir())  # nothing written


def test_the_command_line_becomes_one_request(tmp_path, monkeypatch):
    from lidar_iris_eval.cli import main

    seen = []
    monkeypatch.setitem(eval_cmd.MODE_RUNNERS, "sequence", seen.append)
    main(["eval", str(tmp_path / "seq"), "-d", "m2dp,esf:reference", "--protocol", "2",
          "--protocol", "1", "--radius", "7", "--exclude", "reference", "--candidates", "3",
          "--block-pairs", "1000", "--workers", "2", "--format", "csv", "--ranking",
          "--external", "x=a.npy"])
    (req,) = seen
    assert req.sequences == (tmp_path / "seq",)
    assert req.protocols == ("2", "1")
    assert req.descriptor_text == "m2dp,esf:reference"
    assert (req.settings.radius, req.settings.exclude, req.settings.exclude_name) == \
        (7.0, 300, "reference")
    assert (req.settings.candidates, req.settings.pair_budget) == (3, 1000)
    assert (req.convention.candidates, req.convention.radius) == (None, 7.0)
    assert (req.workers, req.fmt, req.ranking, req.externals) == (2, "csv", True, ("x=a.npy",))
    assert req.command_extra["command"]["convention"] == req.convention.name
    # each run written gets its own copy of the provenance
    assert req.config_extra() == req.command_extra
    assert req.config_extra() is not req.command_extra
