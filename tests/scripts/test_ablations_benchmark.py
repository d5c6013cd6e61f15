"""benchmarks/ablations.py: every row is a variant `stepnft compare` knows, and the verdicts
read the interval on the side the paper claims."""

import math

import pytest

from benchmark_loader import benchmark_module

from stepnft.algos.variants import VARIANTS


@pytest.fixture(scope="module")
def ablations():
    with benchmark_module("ablations") as module:
        yield module


def test_every_ablation_is_a_known_variant_of_stepnft(ablations):
    names = [a.variant for a in ablations.ABLATIONS]
    assert len(set(names)) == len(names)
    for name in [ablations.REFERENCE, *names]:
        assert VARIANTS[name].algo == "stepnft", name
    argv = ablations.compare_argv(ablations.parse_args(["--seeds", "0", "1"]), [0])
    assert argv[argv.index("--algos") + 1:argv.index("--seeds")] == [ablations.REFERENCE, *names]


@pytest.mark.parametrize(("sign", "diff", "expected"), [
    (-1, (-0.10, -0.15, -0.05), "reproduced"),
    (-1, (+0.10, +0.05, +0.15), "contradicted"),
    (-1, (-0.02, -0.08, +0.04), "not separated"),
    (+1, (+0.10, +0.05, +0.15), "reproduced"),
    (+1, (-0.10, -0.15, -0.05), "contradicted"),
    (+1, (0.0, math.nan, math.nan), "–"),
])
def test_verdicts(ablations, sign, diff, expected):
    assert ablations.verdict(sign, diff) == expected


def _write(path, text="x"):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def test_finished_runs_are_kept_and_restored_on_a_new_machine(ablations, tmp_path):
    from stepnft.compare import Job, job_state

    work, keep, new = tmp_path / "work", tmp_path / "keep", tmp_path / "new"
    _write(work / "compare.json", "{}")
    _write(work / "status.json", "{}")
    for name in ("summary.json", "config.yaml", "run.json", "policy/model.safetensors"):
        _write(work / "sft" / "seed0" / name)
    for name in ("summary.json", "metrics.jsonl", "config.yaml", "run.json"):
        _write(work / "runs" / "stepnft" / "seed0" / name)
    _write(work / "runs" / "stepnft" / "seed0" / "checkpoints" / "LATEST")  # large files: not kept
    _write(work / "runs" / "ode" / "seed0" / "checkpoints" / "LATEST")  # unfinished: not kept
    _write(work / "sft" / "seed1" / "summary.json")  # an SFT without its policy is not finished

    assert ablations.keep_finished(work, keep) == 2
    made_on = ablations.machines(keep)
    assert sorted(made_on) == ["runs/stepnft/seed0", "sft/seed0"]
    assert ablations.machines_line(made_on).startswith("Machines (runs are deterministic per CPU family")
    assert (keep / "sft" / "seed0" / "policy" / "model.safetensors").is_file()
    assert not (keep / "runs" / "stepnft" / "seed0" / "checkpoints").exists()
    assert not (keep / "runs" / "ode").exists() and not (keep / "sft" / "seed1").exists()

    _write(new / "runs" / "stepnft" / "seed0" / "metrics.jsonl", "partial")  # an attempt cut short
    assert ablations.restore_finished(keep, new) == 2
    assert (new / "runs" / "stepnft" / "seed0" / "metrics.jsonl").read_text() == "x"
    assert (new / "compare.json").is_file()
    for kind, run_dir in (("sft", new / "sft" / "seed0"), ("train", new / "runs" / "stepnft" / "seed0")):
        assert job_state(Job("j", kind, run_dir, None)) == "finished"
    assert ablations.restore_finished(keep, new) == 0  # already there: nothing replaced
