"""What a command may leave behind (README, "Safety"): no policy that samples NaN is saved, a
failed write is one line with the last checkpoint intact, no command writes into a folder
that holds something of another kind, and the command an error message suggests works."""

import json
import shutil

import pytest
import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

import stepnft.checkpoint
from stepnft.algos.stepnft import StepNFT
from stepnft.checkpoint import load_checkpoint
from stepnft.cli import main
from stepnft.config import load_config
from stepnft.data.demos import generate_demos
from stepnft.policies.base import load_policy, non_finite, non_finite_samples
from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig

pytestmark = pytest.mark.filterwarnings("ignore:Constant:UserWarning")


def run_cli(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def one_line_error(capsys, *argv, code: int = 2) -> str:
    """Run ``stepnft argv``; it must end with ``code`` and one error line on stderr (besides
    progress bars, for a command that got to work), which is returned."""
    got, _, err = run_cli(capsys, *argv)
    lines = [line for line in err.splitlines() if ": error: " in line]
    assert got == code and "Traceback" not in err and len(lines) == 1, (got, err[-2000:])
    assert lines[0].startswith(f"stepnft {argv[0]}: error: ") and err.rstrip().endswith(lines[0]), lines
    return lines[0]


def snapshot(folder) -> dict:
    return {p.relative_to(folder): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


SMALL = ["--iterations", 2, "--episodes-per-iteration", 64, "--env.envs-per-task", 64, "--demos.episodes", 64,
         "--sft.steps", 20, "--eval.episodes", 16, "--eval.during-episodes", 16, "--algo.minibatch-size", 64,
         "--checkpoint-every", 1]
"""The bandit demo (``stepnft.demo_bandit``) at a few seconds' size, a checkpoint every iteration."""


def bandit_args(run_dir, demos) -> list:
    return ["demo-bandit", "--run-dir", run_dir, "--demos.path", demos, *SMALL]


def overflow(policy) -> None:
    """Scale every weight by 1e15: still finite, but sampling overflows to NaN."""
    with torch.no_grad():
        for p in policy.parameters():
            p.mul_(1e15)


def tiny_policy() -> FlowPolicy:
    torch.manual_seed(0)
    return FlowPolicy(FlowPolicyConfig(lang_dim=0, hidden_dim=16, num_layers=1))


@pytest.fixture(scope="module")
def bandit_demos(tmp_path_factory):
    return tmp_path_factory.mktemp("bandit") / "demos"


@pytest.fixture(scope="module")
def bandit_yaml(tmp_path_factory):
    """The bandit demo's config for ``stepnft sft`` and ``train`` (which need --run-dir and
    --demos.path besides)."""
    from stepnft.config import save_config
    from stepnft.demo_bandit import bandit_config

    path = tmp_path_factory.mktemp("bandit-config") / "bandit.yaml"
    save_config(bandit_config(), path)
    return path


@pytest.fixture(scope="module")
def reach_policy(tmp_path_factory):
    return tiny_policy().save_pretrained(tmp_path_factory.mktemp("policies") / "policy")


# --- saved policies sample finite actions (items 2 and 6) --------------------------------------
def test_the_sample_check_finds_overflow_in_finite_weights_and_changes_no_random_stream():
    policy = tiny_policy()
    policy.processor.bind_instructions(["reach"])
    raw = {"state": torch.randn(4, 39), "task": torch.zeros(4, dtype=torch.int64)}
    policy.train()
    rng = torch.get_rng_state()
    assert non_finite_samples(policy, raw) == []
    assert torch.equal(torch.get_rng_state(), rng) and policy.training  # no stream drawn from, mode kept
    overflow(policy)
    assert non_finite(policy.state_dict()) == [] and non_finite_samples(policy, raw) == ["ODE", "Flow-SDE"]


def test_a_run_whose_policy_samples_nan_stops_with_exit_1_and_saves_no_such_policy(capsys, tmp_path, bandit_demos,
                                                                                   monkeypatch):
    """Weights finite but sampling NaN after the second update: the run stops (exit 1) before
    that policy plays, is checkpointed or saved; the first iteration's checkpoint is intact."""
    update, updates = StepNFT.update, []

    def overflowing_update(self, batch):
        metrics = update(self, batch)
        updates.append(1)
        if len(updates) == 2:
            overflow(self.policy)
        return metrics

    monkeypatch.setattr(StepNFT, "update", overflowing_update)
    run = tmp_path / "run"
    line = one_line_error(capsys, *bandit_args(run, bandit_demos), code=1)
    assert "the policy samples non-finite actions (ODE, Flow-SDE) after iteration 2" in line
    assert "the last checkpoint is intact" in line
    assert not (run / "policy").exists()
    ckpt = load_checkpoint(run)
    assert ckpt["state"]["iteration"] == 1
    assert load_config(run / "config.yaml").algo.name == "stepnft"
    for saved in (ckpt["policy"], load_policy(run / "best_policy")):
        saved.processor.bind_instructions(["bandit"])
        assert non_finite_samples(saved, {"state": torch.zeros(2, saved.config.state_dim),
                                          "task": torch.zeros(2, dtype=torch.int64)}) == []


def test_an_sft_policy_that_samples_nan_is_not_saved(capsys, tmp_path, bandit_demos, bandit_yaml, monkeypatch):
    import stepnft.algos.sft

    sft_train = stepnft.algos.sft.sft_train

    def overflowing_sft(policy, *args, **kwargs):
        losses = sft_train(policy, *args, **kwargs)
        overflow(policy)
        return losses

    monkeypatch.setattr(stepnft.algos.sft, "sft_train", overflowing_sft)
    line = one_line_error(capsys, "sft", "--config", bandit_yaml, "--run-dir", tmp_path / "run", "--demos.path",
                          bandit_demos, *SMALL, code=1)
    assert "the SFT policy samples non-finite actions (ODE, Flow-SDE) on its demonstrations" in line
    assert not (tmp_path / "run").exists()  # a failed start leaves nothing


def test_eval_refuses_a_policy_that_samples_nan(capsys, tmp_path):
    policy = tiny_policy()
    overflow(policy)
    policy.save_pretrained(tmp_path / "overflowing")  # finite weights: saved by an earlier stepnft
    line = one_line_error(capsys, "eval", "--policy", tmp_path / "overflowing", "--env.tasks", "reach-v3",
                          "--out", tmp_path / "results.json")
    assert "samples non-finite actions (ODE, Flow-SDE) in the first test state: it cannot be evaluated" in line
    assert not (tmp_path / "results.json").exists()


def test_non_finite_normalisation_statistics_are_refused_at_load(capsys, tmp_path, reach_policy):
    bad = tmp_path / "nan-statistics"
    shutil.copytree(reach_policy, bad)
    statistics = load_file(str(bad / "processor.safetensors"))
    statistics["state_mean"][0] = float("nan")
    save_file(statistics, str(bad / "processor.safetensors"))
    for argv in (["eval", "--policy", bad], ["train", "--init", bad, "--run-dir", tmp_path / "never"]):
        line = one_line_error(capsys, *argv)
        assert f"corrupt policy checkpoint at {bad}: processor state_mean holds non-finite values" in line
    statistics["state_mean"][0], statistics["state_std"][1] = 0.0, 0.0
    save_file(statistics, str(bad / "processor.safetensors"))
    assert "processor state_std must be > 0" in one_line_error(capsys, "eval", "--policy", bad)
    assert not (tmp_path / "never").exists()


def test_a_policy_config_that_is_not_a_json_object_is_one_clear_line(capsys, tmp_path, reach_policy):
    bad = tmp_path / "list-config"
    shutil.copytree(reach_policy, bad)
    (bad / "config.json").write_text("[1, 2]")
    for argv in (["eval", "--policy", bad], ["train", "--init", bad, "--run-dir", tmp_path / "never"]):
        assert "config.json must hold a JSON object, not a list" in one_line_error(capsys, *argv)


# --- a failed write (item 4) ---------------------------------------------------------------------
def test_a_full_disk_at_a_checkpoint_is_one_line_and_keeps_the_last_one(capsys, tmp_path, bandit_demos, monkeypatch):
    save, calls = stepnft.checkpoint.save_file, []

    def full_from_the_second(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise SafetensorError("Error while serializing: IoError(No space left on device)")
        return save(*args, **kwargs)

    monkeypatch.setattr(stepnft.checkpoint, "save_file", full_from_the_second)
    run = tmp_path / "run"
    line = one_line_error(capsys, *bandit_args(run, bandit_demos))
    assert f"could not write checkpoint iter_000002 into {run / 'checkpoints'} (" in line and "No space left" in line
    assert f"the previous checkpoint is intact: free some space, then `stepnft train --resume {run}`" in line
    assert (run / "checkpoints" / "LATEST").read_text() == "iter_000001"
    assert load_checkpoint(run)["state"]["iteration"] == 1 and not list((run / "checkpoints").glob(".tmp-*"))


# --- folders of one kind (items 7 and 8) -----------------------------------------------------------
@pytest.fixture(scope="module")
def run_folder(tmp_path_factory):
    """A folder holding a training run (with a checkpoint) and a folder of notes."""
    root = tmp_path_factory.mktemp("folders")
    run = root / "run"
    (run / "checkpoints" / "iter_000004").mkdir(parents=True)
    (run / "checkpoints" / "LATEST").write_text("iter_000004")
    (run / "run.json").write_text('{"kind": "train"}')
    (run / "config.yaml").write_text("seed: 0\n")
    (root / "notes").mkdir()
    (root / "notes" / "todo.txt").write_text("keep me")
    return root


@pytest.mark.parametrize("argv, flag", [
    (["demos", "--env.tasks", "reach-v3", "--demos.path", "{folder}"], "--demos.path"),
    (["eval", "--policy", "{policy}", "--env.tasks", "reach-v3", "--video-dir", "{folder}"], "--video-dir"),
    (["compare", "--config", "configs/quickstart.yaml", "--env-steps", 100, "--out", "{folder}"], "--out"),
    (["sft", "--run-dir", "{folder}"], "--run-dir"),
])
def test_no_command_writes_into_a_folder_of_another_kind(capsys, run_folder, reach_policy, argv, flag):
    for name, held in (("run", "a training run"), ("notes", "other files (todo.txt)")):
        folder = run_folder / name
        before = snapshot(folder)
        filled = [str(a).format(folder=folder, policy=reach_policy) for a in argv]
        line = one_line_error(capsys, *filled)
        if argv[0] == "sft":
            assert "choose another --run-dir" in line
        else:
            assert f"{folder} holds {held}" in line and f"choose another {flag} (a new or empty folder)" in line
        assert snapshot(folder) == before


def test_eval_out_is_checked_before_any_work(capsys, tmp_path, run_folder, reach_policy):
    # A folder: refused before the (missing) policy is even looked at.
    line = one_line_error(capsys, "eval", "--policy", tmp_path / "no-policy", "--out", run_folder / "notes")
    assert f"--out {run_folder / 'notes'} is a folder: give a file name, e.g. --out {run_folder / 'notes' / 'eval.json'}" in line
    line = one_line_error(capsys, "eval", "--policy", tmp_path / "no-policy", "--out", run_folder / "run" / "config.yaml")
    assert "exists and holds no stepnft eval results: choose another --out" in line
    assert (run_folder / "run" / "config.yaml").read_text() == "seed: 0\n"
    earlier = tmp_path / "eval.json"  # the results of an earlier evaluation are replaced
    earlier.write_text(json.dumps({"tasks": {}, "average": 0.0}))
    code, _, _ = run_cli(capsys, "eval", "--policy", reach_policy, "--env.tasks", "reach-v3", "--eval.episodes", 1,
                         "--env.envs-per-task", 1, "--env.max-episode-steps", 4, "--out", earlier)
    assert code == 0 and json.loads(earlier.read_text())["episodes"] == 1


def test_task_episodes_must_name_tasks_of_the_simulator(capsys, tmp_path):
    for argv in (["demos", "--demos.path", tmp_path / "demos"], ["train", "--run-dir", tmp_path / "run"]):
        line = one_line_error(capsys, *argv, "--env.tasks", "reach-v3", "--demos.task-episodes", "nope-v3", 2)
        assert "--demos.task-episodes names nope-v3, not a MetaWorld task" in line
    assert list(tmp_path.iterdir()) == []


def test_task_episodes_of_tasks_not_played_are_ignored():
    """The quickstart config's counts (door-open, drawer-open) serve a run on any subset of tasks."""
    from stepnft.config import DemoConfig
    from stepnft.data.demos import check_task_episodes
    from stepnft.envs import get_simulator

    cfg = DemoConfig(episodes=3, task_episodes={"door-open-v3": 1})
    check_task_episodes(cfg, get_simulator("metaworld"))  # the run may play only reach-v3
    assert cfg.count("reach-v3") == 3 and cfg.count("door-open-v3") == 1


def test_resume_follows_no_latest_out_of_its_run_and_says_how_to_repair_it(capsys, tmp_path):
    from stepnft.checkpoint import save_checkpoint

    runs = {}
    for name in ("mine", "other"):
        runs[name] = tmp_path / name
        runs[name].mkdir()
        (runs[name] / "run.json").write_text('{"kind": "train"}')
        policy = tiny_policy()
        save_checkpoint(runs[name], 2, policy, {"env_steps": 2, "torch_rng": torch.get_rng_state()})
        save_checkpoint(runs[name], 4, policy, {"env_steps": 4, "torch_rng": torch.get_rng_state()})
    latest = runs["mine"] / "checkpoints" / "LATEST"
    latest.write_text("../../other/checkpoints/iter_000004")
    with pytest.raises(ValueError, match=r"names '../../other/checkpoints/iter_000004', not a checkpoint folder of "
                                         rf"this run; point it at its newest checkpoint \(`echo iter_000004 > {latest}`\)"):
        load_checkpoint(runs["mine"])
    latest.unlink()  # deleted: a new run there says resume, resume says how
    line = one_line_error(capsys, "train", "--run-dir", runs["mine"])
    assert f"continue it with `stepnft train --resume {runs['mine']}`" in line
    with pytest.raises(ValueError, match=rf"has no checkpoints/LATEST; .*`echo iter_000004 > {latest}`"):
        load_checkpoint(runs["mine"])
    latest.write_text("iter_000004")  # the hint
    assert load_checkpoint(runs["mine"])["state"]["env_steps"] == 4
    shutil.rmtree(runs["mine"] / "checkpoints")  # no checkpoint, and a file of the user's: kept, the hint says where
    (runs["mine"] / "notes.txt").write_text("mine")
    line = one_line_error(capsys, "train", "--run-dir", runs["mine"])
    assert f"without a checkpoint to continue from: choose another --run-dir, or delete that one (`rm -r {runs['mine']}`)" in line


# --- messages that lead somewhere (items 1 and 9) -------------------------------------------------
def test_max_attempts_works_by_flag_and_yaml_and_its_cap_names_it(capsys, tmp_path):
    code, out, _ = run_cli(capsys, "demos", "--env.tasks", "reach-v3", "--demos.episodes", 2, "--demos.max-attempts",
                           10, "--demos.path", tmp_path / "x", "--env.max-episode-steps", 100)
    assert code == 0 and "wrote 2 successful episodes x 1 tasks" in out
    assert json.loads((tmp_path / "x" / "manifest.json").read_text())["generator"]["max_attempts"] == 10
    config = tmp_path / "c.yaml"
    config.write_text("demos:\n  max_attempts: 10\n")
    assert load_config(config).demos.max_attempts == 10
    line = one_line_error(capsys, "demos", "--env.tasks", "reach-v3", "--demos.episodes", 2, "--demos.max-attempts",
                          2, "--demos.action-noise", 5, "--demos.path", tmp_path / "capped")
    assert "raise --demos.max-attempts above 2" in line and not (tmp_path / "capped").exists()


def test_the_corrupt_demonstrations_hint_works(capsys, tmp_path, bandit_yaml):
    demos = generate_demos("bandit", 64, tmp_path / "demos", progress=False, simulator="bandit", successful_only=False)
    (demos / "manifest.json").write_text("{broken")
    argv = ["sft", "--config", bandit_yaml, "--run-dir", tmp_path / "run", "--demos.path", demos, *SMALL]
    line = one_line_error(capsys, *argv)
    assert f"corrupt demonstrations at {demos}" in line and f"delete the folder (`rm -r {demos}`)" in line
    shutil.rmtree(demos)  # the hint
    assert run_cli(capsys, *argv)[0] == 0 and (tmp_path / "run" / "policy" / "config.json").is_file()


def test_the_sft_run_hint_works(capsys, tmp_path, bandit_demos, bandit_yaml):
    sft = tmp_path / "sft"
    argv = ["--config", bandit_yaml, "--demos.path", bandit_demos, *SMALL]
    assert run_cli(capsys, "sft", "--run-dir", sft, *argv)[0] == 0
    line = one_line_error(capsys, "train", "--run-dir", sft, *argv)
    hint = line.split("`")[1]
    assert hint == f"stepnft train --config {sft}/config.yaml --init {sft}/policy --run-dir NEW_DIR"
    code, _, err = run_cli(capsys, *hint.replace("NEW_DIR", str(tmp_path / "rl")).split()[1:])
    assert code == 0, err[-2000:]
    assert (tmp_path / "rl" / "policy" / "config.json").is_file()


def test_config_naming_a_folder_says_so(capsys, tmp_path):
    line = one_line_error(capsys, "train", "--config", tmp_path)
    assert f"config file {tmp_path} is a folder: give a YAML file" in line


def test_a_start_killed_before_its_first_checkpoint_is_cleared_by_the_next_start(tmp_path):
    """kill -9 before the first checkpoint leaves run.json, config.yaml, metrics and an SFT policy:
    nothing resumes from them, so the next start of the same kind empties the folder (and says so);
    a folder with a checkpoint, a summary, another kind or a file of the user's is left alone."""
    from stepnft.runs import clear_interrupted_start

    run = tmp_path / "run"
    (run / "sft_policy").mkdir(parents=True)
    (run / "run.json").write_text('{"kind": "train"}')
    (run / "config.yaml").write_text("seed: 0\n")
    (run / "metrics.jsonl").write_text("{}\n")
    assert not clear_interrupted_start(run, "sft") and (run / "run.json").is_file()  # another kind
    (run / "checkpoints").mkdir()
    (run / "checkpoints" / "iter_000002").mkdir()
    assert not clear_interrupted_start(run, "train")  # it resumes
    shutil.rmtree(run / "checkpoints")
    (run / "notes.txt").write_text("mine")
    assert not clear_interrupted_start(run, "train")  # the user's file
    (run / "notes.txt").unlink()
    assert clear_interrupted_start(run, "train") and list(run.iterdir()) == []
