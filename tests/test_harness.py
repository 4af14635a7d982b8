"""The benchmark harness's record: the commit it names and the digest of the sources."""

import json
import pathlib
import shutil
import types

import numpy as np

from benchmarks import run
from benchmarks._timing import time_fns


def test_the_record_names_the_given_commit_and_the_sources_that_ran(monkeypatch, tmp_path):
    result = {"title": "fake", "rows": [{"case": "a", "median_s": 0.5}], "ratios": {"r": 2.0}}
    module = types.SimpleNamespace(run=lambda quick: dict(result, quick_seen=quick))
    monkeypatch.setattr(run.importlib, "import_module", lambda name: module)
    out = tmp_path / "r.json"
    assert run.main(["fit", "--quick", "--json", str(out), "--commit", "abc1234"]) == 0
    record = json.loads(out.read_text())
    assert record["commit"] == "abc1234" and record["quick_seen"] is True
    assert record["sources"] == run.sources_digest()
    assert record["name"] == "fit" and record["rows"] == result["rows"]
    # without --commit, the checkout's own (or "unknown" without git)
    assert run.main(["fit", "--json", str(out)]) == 0
    assert json.loads(out.read_text())["commit"] == run._commit()


def test_sources_digest_follows_the_sources_and_nothing_else(tmp_path):
    checkout = pathlib.Path(run.__file__).resolve().parents[1]
    for name in ("volshade", "benchmarks"):
        shutil.copytree(checkout / name, tmp_path / name,
                        ignore=shutil.ignore_patterns("__pycache__", "results"))
    first = run.sources_digest(tmp_path)
    assert len(first) == 16 and first == run.sources_digest(tmp_path)
    assert first == run.sources_digest()  # the copy holds the same sources
    (tmp_path / "README.md").write_text("not a source")
    (tmp_path / "volshade" / "data.csv").write_text("1,2")
    assert run.sources_digest(tmp_path) == first
    source = tmp_path / "volshade" / "lao.py"
    source.write_text(source.read_text() + "\n")
    edited = run.sources_digest(tmp_path)
    assert edited != first
    source.rename(tmp_path / "volshade" / "lao_renamed.py")  # a path counts too
    assert run.sources_digest(tmp_path) not in (first, edited)


def test_the_record_is_strict_json(monkeypatch, tmp_path):
    # found by a review: a NaN (a row with nothing to time) was written as a bare NaN
    # token, which is not JSON (a browser's JSON.parse refuses the file)
    result = {"title": "fake", "rows": [{"case": "agree", "median_s": float("nan"),
                                         "max": float("inf"), "mean": np.float32("nan")}],
              "ratios": {"r": 2.0}}
    module = types.SimpleNamespace(run=lambda quick: result)
    monkeypatch.setattr(run.importlib, "import_module", lambda name: module)
    out = tmp_path / "r.json"
    assert run.main(["fit", "--json", str(out)]) == 0

    def refuse(token):
        raise ValueError(token)

    record = json.loads(out.read_text(), parse_constant=refuse)
    assert record["rows"] == [{"case": "agree", "median_s": None, "max": None, "mean": None}]
    assert record["ratios"] == {"r": 2.0}


def test_compared_functions_are_timed_interleaved():
    calls = []

    def fn(name):
        def call(x):
            calls.append(name)
            return x
        return call

    out = time_fns({"a": fn("a"), "b": fn("b"), "c": fn("c")}, 1.0, repeats=3)
    # first calls apart, then rounds of one call each, in rotated order
    assert calls == ["a", "b", "c", "a", "b", "c", "b", "c", "a", "c", "a", "b"]
    for result in out.values():
        assert len(result["times_s"]) == 3 and result["first_call_s"] >= 0
        assert result["median_s"] == sorted(result["times_s"])[1]
