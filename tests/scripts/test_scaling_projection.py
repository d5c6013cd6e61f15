"""benchmarks/scaling.py --project-from: the projection recomputed from a saved measurement is
the one the measurement wrote, and another run's settings move it the way the model says."""

import json
from pathlib import Path

import pytest
from benchmark_loader import ROOT, benchmark_module

SAVED = ROOT / "benchmarks" / "results" / "scaling"


@pytest.fixture(scope="module")
def scaling():
    with benchmark_module("scaling") as module:
        yield module


def test_projection_from_saved_figures_reproduces_the_saved_one(scaling, tmp_path):
    saved = json.loads((SAVED / "scaling.json").read_text())
    a = saved["args"]
    record = scaling.main(["--project-from", str(SAVED), "--config", str(ROOT / a["config"]), "--out", str(tmp_path),
                           "--project-envs", str(a["project_envs"]), "--cores-per-machine", str(a["cores_per_machine"]),
                           "--project-iterations", str(a["project_iterations"])])
    for mine, theirs in zip(record["projection"], saved["projection"], strict=True):
        assert mine["bottleneck"] == theirs["bottleneck"]
        assert mine["iteration_s"] == pytest.approx(theirs["iteration_s"])
    assert (tmp_path / "projection.md").is_file() and json.loads((tmp_path / "projection.json").read_text())


def test_more_envs_and_shorter_episodes_move_the_projection_as_the_model_says(scaling, tmp_path):
    base = ["--project-from", str(SAVED), "--config", str(ROOT / "configs" / "quickstart.yaml"), "--out", str(tmp_path)]
    short = scaling.main(base + ["--episode-steps", "100"])["projection"]
    long = scaling.main(base + ["--episode-steps", "200"])["projection"]
    wide = scaling.main(base + ["--episode-steps", "200", "--project-envs", "640"])["projection"]
    assert long[0]["rollout_s"] == pytest.approx(2 * short[0]["rollout_s"])
    assert wide[0]["update_s"] == pytest.approx(10 * long[0]["update_s"])
    assert all(w["iteration_s"] > l["iteration_s"] for w, l in zip(wide, long))
