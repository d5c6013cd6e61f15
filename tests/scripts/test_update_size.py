"""benchmarks/update_size.py: the first update's size apart from the later ones, the success
figures of a run read from its metrics, and one-line errors for bad input."""

import json

import pytest
from benchmark_loader import benchmark_module


@pytest.fixture(scope="module")
def update_size():
    with benchmark_module("update_size") as module:
        yield module


def write_run(folder, records):
    folder.mkdir(parents=True)
    (folder / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    return folder


def test_a_run_that_moved_too_far_reads_as_such(update_size, tmp_path):
    run = write_run(tmp_path / "ppo", [
        {"iteration": 0, "env_steps": 0, "charts/validation_success_rate": 0.5},
        {"iteration": 1, "env_steps": 100, "charts/rollout_success_rate": 0.7, "losses/approx_kl": 35.0,
         "losses/clipfrac": 0.95},
        *({"iteration": i, "env_steps": 100 * i, "charts/rollout_success_rate": 0.0, "losses/approx_kl": kl,
           "losses/clipfrac": 0.9} for i, kl in ((2, 6.0), (3, 8.0), (4, 2.0))),
        {"iteration": 4, "env_steps": 400, "charts/validation_success_rate": 0.1},
        {"final": True, "env_steps": 400, "charts/success_rate": 0.0}])
    row = update_size.summarise(run, last=2)
    assert row["iterations"] == 5 and row["env_steps"] == 400  # the records after the start (no final line)
    assert row["first_kl"] == 35.0 and row["later_kl_median"] == 6.0 and row["later_clipfrac_median"] == 0.9
    assert row["rollout_first"] == 0.7 and row["rollout_last"] == 0.0
    assert row["validation"] == [(0, 0.5), (4, 0.1)]
    text = update_size.table({"ppo lr 1e-4": row}, 2)
    assert "| ppo lr 1e-4 | 5 | 400 | 35 | 6 | 0.95 | 0.90 | 0.70 | 0.00 | 0.50 (0), 0.10 (4) |" in text


def test_bad_input_is_one_line_and_exit_2(update_size, tmp_path, capsys):
    write_run(tmp_path / "a", [{"iteration": 0, "env_steps": 0}])
    for argv in ([str(tmp_path / "nope")], [str(tmp_path / "a"), "--labels", "x", "y"]):
        with pytest.raises(SystemExit) as err:
            update_size.parse_args(argv)
        assert err.value.code == 2
    assert "no metrics.jsonl" in capsys.readouterr().err


def test_the_recorded_command_keeps_a_label_with_spaces_one_argument(update_size, monkeypatch):
    import shlex
    import sys

    argv = ["benchmarks/update_size.py", "runs/a", "--labels", "ppo lr 1e-4"]
    monkeypatch.setattr(sys, "argv", argv)
    assert shlex.split(update_size.command())[1:] == argv  # provenance.command, shared by every benchmark


def test_runs_of_one_seed_in_different_variants_get_their_own_rows(update_size, tmp_path):
    for variant in ("ppo", "grpo"):
        write_run(tmp_path / variant / "seed1", [{"iteration": 0, "env_steps": 0}])
    assert update_size.default_labels([str(tmp_path / "ppo/seed1"), str(tmp_path / "grpo/seed1")]) == [
        "ppo/seed1", "grpo/seed1"]
    assert update_size.default_labels([str(tmp_path / "ppo/seed1")]) == ["seed1"]
    with pytest.raises(SystemExit) as err:
        update_size.parse_args([str(tmp_path / "ppo/seed1"), str(tmp_path / "grpo/seed1"), "--labels", "x", "x"])
    assert err.value.code == 2
