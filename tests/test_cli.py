"""The ``stepnft`` command line: help, and bad input ending in one line on stderr, exit code 2,
with nothing already written lost."""

import dataclasses
import json
import shutil

import pytest
import torch

from stepnft.checkpoint import save_checkpoint
from stepnft.cli import COMMANDS, CONFIG_SECTIONS, _config_from_argv, main
from stepnft.config import EnvConfig, TrainConfig, save_config
from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig


def run_cli(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def snapshot(folder) -> dict:
    return {p.relative_to(folder): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def tiny_policy() -> FlowPolicy:
    torch.manual_seed(0)
    return FlowPolicy(FlowPolicyConfig(lang_dim=0, hidden_dim=16, num_layers=1))


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    """A finished-looking run (config, checkpoint, metrics, summary), a saved policy, a file."""
    root = tmp_path_factory.mktemp("cli")
    run = root / "run"
    cfg = TrainConfig(run_dir=str(run), iterations=2, num_threads=1,
                      env=EnvConfig(tasks=["reach-v3"], envs_per_task=1, max_episode_steps=10),
                      policy=FlowPolicyConfig(lang_dim=0, hidden_dim=16, num_layers=1))
    run.mkdir()
    save_config(cfg, run / "config.yaml")
    policy = tiny_policy()
    save_checkpoint(run, 2, policy, {"env_steps": 20, "before": {}, "torch_rng": torch.get_rng_state()})
    (run / "metrics.jsonl").write_text(json.dumps({"iteration": 0, "env_steps": 0}) + "\n")
    (run / "summary.json").write_text("{}")
    policy.save_pretrained(root / "policy")
    (root / "a-file").write_text("not a folder")
    return root


@pytest.fixture
def existing_run(workspace):
    """The run folder; the test fails if a command changed or removed anything in it."""
    run = workspace / "run"
    before = snapshot(run)
    yield run
    after = snapshot(run)
    assert {k: after.get(k) for k in before} == before


def assert_one_line_error(code, err, command):
    assert code == 2
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"stepnft {command}: error: "), err
    return lines[0]


def test_help_lists_every_command_and_config_section(capsys):
    code, out, _ = run_cli(capsys, "--help")
    assert code == 0
    assert all(name in out for name in COMMANDS)
    assert set(CONFIG_SECTIONS) == {f.name for f in dataclasses.fields(TrainConfig)
                                    if dataclasses.is_dataclass(getattr(TrainConfig(), f.name))}
    assert all(f"--{s}.*" in out for s in CONFIG_SECTIONS)

    code, out, _ = run_cli(capsys, "train", "--help")
    assert code == 0
    assert all(f"--{s}." in out for s in CONFIG_SECTIONS)
    assert "--config" in out and "--resume" in out
    assert "{next,x0}" in out and "{rank,wmse,pos,neg}" in out  # choice fields list their choices
    assert "--algo.name" in out and "stepnft" in out
    for command in ("sft", "eval", "demos", "demo-bandit"):
        assert run_cli(capsys, command, "--help")[0] == 0


def test_help_states_the_range_of_every_bounded_flag(capsys):
    code, out, _ = run_cli(capsys, "train", "--help")
    text = " ".join(line.strip("│ ") for line in out.splitlines())  # tyro's boxes wrap the help
    assert code == 0 and "Takes an integer in [0, 2147483647]." in text  # --seed
    assert "Takes a finite number in (0, 1]." in text  # --algo.lr
    code, out, _ = run_cli(capsys, "eval", "--help")
    assert "Takes an integer in [0, 16777216]." in " ".join(line.strip("│ ") for line in out.splitlines())


@pytest.mark.parametrize("argv, expected", [
    (["demos", "--tasks", "reach-v3"], "--tasks is now --env.tasks"),
    (["demos", "--env.tasks", "reach-v3", "--out=d"], "--out is now --demos.path"),
    (["eval", "--episodes", "7"], "--episodes is now --eval.episodes"),
    (["eval", "--seed", "2"], "--seed is now --eval.seed"),
    (["demo-bandit", "--beta", "2"], "--beta is now --algo.beta"),
])
def test_flags_of_earlier_releases_name_their_replacement(capsys, argv, expected):
    line = assert_one_line_error(*run_cli(capsys, *argv)[::2], argv[0])
    assert expected in line and "were removed" in line


def test_comma_separated_tasks_work_everywhere():
    cfg, _ = _config_from_argv(["--env.tasks", "reach-v3,push-v3"], "stepnft train", True)
    assert cfg.env.tasks == ["reach-v3", "push-v3"]
    cfg, _ = _config_from_argv(["--env.tasks", "reach-v3,push-v3", "door-open-v3", "--env.randomize",
                                      "friction,mass"], "stepnft train", True)
    assert cfg.env.tasks == ["reach-v3", "push-v3", "door-open-v3"] and cfg.env.randomize == ["friction", "mass"]


@pytest.mark.parametrize("argv, expected", [
    (["train", "--env.tasks", "reach-v3", "nope-v3"], "unknown MetaWorld task 'nope-v3'; valid names: assembly-v3"),
    (["train", "--algo.lr", "-1"], "--algo.lr must be a finite number in (0, 1], got -1.0"),
    (["train", "--env.max-episode-steps", "900"], "--env.max-episode-steps must be in [1, 500] for metaworld, got 900"),
    (["train", "--iterations", "-1"], "--iterations must be an integer in [0, 100000000], got -1"),
    (["train", "--seed", "-1"], "--seed must be an integer in [0, 2147483647], got -1"),
    (["sft", "--policy.n-exec", "9"], "--policy.n-exec (9) must be <= --policy.horizon (4)"),
    (["eval", "--env.tasks", "nope-v3"], "unknown MetaWorld task 'nope-v3'"),
    (["eval", "--eval.episodes", "-1"], "--eval.episodes must be an integer in [0, 16777216], got -1"),
    (["eval", "--env.envs-per-task", "0"], "--env.envs-per-task must be an integer in [1, 4096], got 0"),
    (["eval", "--device", "gpu"], "--device must be cpu, cuda or cuda:N, got 'gpu'"),
    (["train", "--algo.name", "dqn"], "--algo.name must be one of stepnft, ppo, grpo, got 'dqn'"),
    (["train", "--env.name", "gazebo"], "--env.name must be one of metaworld, bandit, libero, maniskill, gym, got 'gazebo'"),
    (["train", "--algo.sde-steps", "one"], "--algo.sde-steps=one needs --algo.record-steps=one"),
    (["train", "--algo.lr", "inf"], "--algo.lr must be a finite number in (0, 1], got inf"),
    (["train", "--algo.noise-level", "1e6"], "--algo.noise-level must be a finite number in [0, 10], got 1000000.0"),
    (["train", "--algo.noise-level", "inf"], "--algo.noise-level must be a finite number in [0, 10], got inf"),
    (["train", "--algo.beta", "inf"], "--algo.beta must be a finite number in (0, 1000], got inf"),
    (["train", "--algo.kl-beta", "nan"], "--algo.kl-beta must be a finite number in [0, 1000], got nan"),
    (["train", "--algo.grad-clip", "nan"], "--algo.grad-clip must be a finite number in (0, 1000000], got nan"),
    (["train", "--algo.max-drift", "0"], "--algo.max-drift must be a finite number in (0, 1000000] or None, got 0.0"),
    (["train", "--algo.ema-horizon", "0"], "--algo.ema-horizon must be an integer in [1, 100000000] or None, got 0"),
    (["train", "--algo.name", "ppo", "--algo.noise-level", "inf"], "--algo.noise-level must be a finite number"),
    (["train", "--algo.name", "ppo", "--algo.noise-level", "0"], "--algo.noise-level must be > 0 for PPO and GRPO"),
    (["train", "--algo.name", "ppo", "--algo.critic-lr", "inf"], "--algo.critic-lr must be a finite number in (0, 1], got inf"),
    (["train", "--algo.name", "ppo", "--algo.clip-coef", "inf"], "--algo.clip-coef must be a finite number in (0, 10], got inf"),
    (["train", "--algo.name", "grpo", "--algo.clip-coef", "nan"], "--algo.clip-coef must be a finite number in (0, 10], got nan"),
    (["train", "--algo.name", "grpo", "--algo.group-size", "1"], "--algo.group-size must be >= 2 for GRPO"),
    (["train", "--sft.lr", "inf"], "--sft.lr must be a finite number in (0, 1], got inf"),
    (["train", "--sft.weight-decay", "inf"], "--sft.weight-decay must be a finite number in [0, 1], got inf"),
    (["train", "--policy.state-min-std", "0"], "--policy.state-min-std must be a finite number in (0, 1000000], got 0.0"),
    (["train", "--policy.time-embed-dim", "63"], "--policy.time-embed-dim must be even"),
    (["train", "--policy.cameras", "corner"], "--policy.cameras ['corner'] differ from --env.cameras []"),
    (["train", "--num-threads", "0"], "--num-threads must be an integer in [1, 1024], got 0"),
    (["train", "--num-threads", "-2"], "--num-threads must be an integer in [1, 1024], got -2"),
    (["train", "--env-step-budget", "-1"], "--env-step-budget must be an integer in [1, 1000000000000] or None, got -1"),
    (["train", "--eval.every", "-1"], "--eval.every must be an integer in [0, 100000000], got -1"),
    (["train", "--eval.validation-seed", "5"], "--eval.validation-seed (5) must be >= --eval.seed + --eval.episodes (100)"),
    (["train", "--env.num-workers", "-1"], "--env.num-workers must be an integer in [0, 256], got -1"),
    (["train", "--env.randomize", "nope"], "--env.randomize: unknown perturbation 'nope'"),
    (["train", "--ray.address", "auto"], "--ray.address needs rollout workers on the cluster: set --ray.workers N"),
    (["demos", "--demos.action-noise", "nan"], "--demos.action-noise must be a finite number in [0, 10], got nan"),
    (["demos", "--demos.max-attempts", "2"], "--demos.max-attempts must be >= the demonstrations wanted (5), got 2"),
    (["train", "--iterations", "notanint"], "Error parsing --iterations"),
])
def test_invalid_values_are_one_line(capsys, existing_run, argv, expected):
    command = argv[0]
    if command in ("train", "sft"):
        argv = argv + ["--run-dir", str(existing_run)]
    line = assert_one_line_error(*run_cli(capsys, *argv)[::2], command)
    assert expected in line


@pytest.mark.parametrize("yaml_text, expected", [
    ("iterations: 3\nnot_a_key: 1\n", "unknown config key 'not_a_key'"),
    ("algo:\n  lrr: 0.1\n", "unknown config key 'algo.lrr'"),
    ("iterations: many\n", "iterations must be an integer in [0, 100000000], got 'many'"),
    ("seed: true\n", "seed must be an integer in [0, 2147483647], got True"),
    ("env:\n  tasks: 5\n", "env.tasks must be a list of names, got 5"),
    ("algo:\n  lr: -1\n", "algo.lr must be a finite number in (0, 1], got -1"),
    ("algo:\n  name: ppo\n  critic_lr: .inf\n", "algo.critic_lr must be a finite number in (0, 1], got inf"),
    ("policy:\n  n_exec: 2.5\n", "policy.n_exec must be an integer in [1, 1024], got 2.5"),
    ("iterations: [1\n", "is not valid YAML"),
    ("algo:\n  target: x1\n", "algo.target must be one of next, x0, got 'x1'"),
    ("algo:\n  name: dqn\n", "algo.name must be one of stepnft, ppo, grpo, got 'dqn'"),
])
def test_bad_yaml_configs_are_one_line(capsys, tmp_path, existing_run, yaml_text, expected):
    config = tmp_path / "config.yaml"
    config.write_text(yaml_text)
    line = assert_one_line_error(*run_cli(capsys, "train", "--config", config, "--run-dir", existing_run)[::2], "train")
    assert expected in line
    line = assert_one_line_error(*run_cli(capsys, "train", "--config", tmp_path / "missing.yaml")[::2], "train")
    assert "not found" in line


def test_a_yaml_config_is_read_and_flags_override_it(tmp_path):
    config = tmp_path / "config.yaml"
    config.write_text("iterations: 7\nenv:\n  tasks: reach-v3,push-v3\nalgo:\n  lr: 0.001\n")
    cfg, resume = _config_from_argv(["--config", str(config), "--algo.lr", "0.002"], "stepnft train", True)
    assert not resume and cfg.iterations == 7 and cfg.env.tasks == ["reach-v3", "push-v3"] and cfg.algo.lr == 0.002


def test_a_yaml_config_reads_exponents_as_numbers(tmp_path):
    config = tmp_path / "config.yaml"  # YAML 1.1 (PyYAML's) reads 3e-5 as a string; a user writes it
    config.write_text("algo:\n  lr: 3e-5\n  critic_lr: 1E-3\n  name: ppo\nenv:\n  tasks: [reach-v3]\n")
    cfg, _ = _config_from_argv(["--config", str(config)], "stepnft train", True)
    assert cfg.algo.lr == 3e-5 and cfg.algo.critic_lr == 1e-3 and cfg.env.tasks == ["reach-v3"]


def test_missing_or_corrupt_policy_for_eval(capsys, workspace, tmp_path):
    line = assert_one_line_error(*run_cli(capsys, "eval", "--policy", tmp_path / "nowhere")[::2], "eval")
    assert "no policy checkpoint at" in line

    corrupt = tmp_path / "corrupt"
    shutil.copytree(workspace / "policy", corrupt)
    (corrupt / "model.safetensors").write_bytes(b"\x00garbage" * 10)
    line = assert_one_line_error(*run_cli(capsys, "eval", "--policy", corrupt)[::2], "eval")
    assert "corrupt policy checkpoint" in line

    (corrupt / "config.json").write_text("{not json")
    assert "corrupt policy checkpoint" in assert_one_line_error(*run_cli(capsys, "eval", "--policy", corrupt)[::2], "eval")


def test_resume_refuses_what_it_cannot_continue(capsys, workspace, tmp_path):
    line = assert_one_line_error(*run_cli(capsys, "train", "--resume", tmp_path / "nowhere")[::2], "train")
    assert "no config.yaml there" in line

    started = tmp_path / "started"
    started.mkdir()
    shutil.copy(workspace / "run" / "config.yaml", started)
    line = assert_one_line_error(*run_cli(capsys, "train", "--resume", started)[::2], "train")
    assert "holds no stepnft run, not a training run" in line
    (started / "run.json").write_text('{"kind": "train"}')
    line = assert_one_line_error(*run_cli(capsys, "train", "--resume", started)[::2], "train")
    assert "no checkpoint to resume" in line
    (started / "run.json").write_text('{"kind": "sft"}')
    line = assert_one_line_error(*run_cli(capsys, "train", "--resume", started)[::2], "train")
    assert "holds an SFT run, not a training run" in line

    line = assert_one_line_error(*run_cli(capsys, "train", "--resume", workspace / "run", "--seed", "9")[::2], "train")
    assert ("takes no other flags than --ray.*, --device, --gradient-checkpointing, --iterations and "
            "--env-step-budget; drop: --seed") in line


def test_resume_of_a_corrupt_checkpoint_loses_nothing(capsys, workspace, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(workspace / "run", run)
    (run / "checkpoints" / "iter_000002" / "policy" / "model.safetensors").write_bytes(b"garbage")
    before = snapshot(run)
    line = assert_one_line_error(*run_cli(capsys, "train", "--resume", run)[::2], "train")
    assert "is corrupt or incomplete" in line
    after = snapshot(run)
    assert {k: after.get(k) for k in before} == before


def test_unwritable_outputs_fail_before_any_work(capsys, workspace):
    under_a_file = workspace / "a-file" / "sub"
    policy = workspace / "policy"
    cases = [
        (["train", "--run-dir", under_a_file, "--env.tasks", "reach-v3"], "train", "choose another --run-dir"),
        (["sft", "--run-dir", under_a_file], "sft", "choose another --run-dir"),
        (["demos", "--demos.path", under_a_file, "--env.tasks", "reach-v3"], "demos", "choose another --demos.path"),
        (["eval", "--policy", policy, "--env.tasks", "reach-v3", "--out", under_a_file / "r.json"], "eval",
         "choose another --out"),
        (["eval", "--policy", policy, "--env.tasks", "reach-v3", "--video-dir", under_a_file], "eval",
         "choose another --video-dir"),
    ]
    for argv, command, expected in cases:
        line = assert_one_line_error(*run_cli(capsys, *argv)[::2], command)
        assert f"cannot write to {under_a_file}" in line and expected in line
    assert (workspace / "a-file").read_text() == "not a folder"


@pytest.mark.parametrize("argv", [["train", "--iterations", "notanint"], ["train", "--no-such-flag", "1"],
                                  ["eval", "--eval.episodes", "x"]])
def test_argument_errors_are_one_line_too(capsys, argv):
    assert_one_line_error(*run_cli(capsys, *argv)[::2], argv[0])


def test_unknown_command(capsys):
    code, _, err = run_cli(capsys, "trian")
    assert code == 2 and err.startswith("stepnft: error: unknown command 'trian'") and "train" in err


def test_eval_writes_its_results(capsys, workspace, tmp_path):
    out = tmp_path / "results" / "eval.json"
    code, stdout, _ = run_cli(capsys, "eval", "--policy", workspace / "policy", "--env.tasks", "reach-v3",
                              "--eval.episodes", 3, "--env.envs-per-task", 2, "--env.max-episode-steps", 10, "--out", out)
    assert code == 0 and "reach-v3" in stdout
    result = json.loads(out.read_text())
    assert result["tasks"]["reach-v3"]["episodes"] == 3 and result["episodes"] == 3


def test_policy_configs_of_the_wrong_shape_are_one_line(capsys, workspace, tmp_path):
    bad = tmp_path / "bad"
    shutil.copytree(workspace / "policy", bad)
    config = json.loads((bad / "config.json").read_text())
    cases = [(json.dumps([1, 2]), ""),
             (json.dumps({**config, "hidden_dim": "wide"}), "policy.hidden_dim must be an integer in [1, 16384], got 'wide'"),
             (json.dumps({**config, "n_exec": 2.5}), "policy.n_exec must be an integer in [1, 1024], got 2.5"),
             (json.dumps({**config, "num_inference_steps": 4.5}), "policy.num_inference_steps must be an integer"),
             (json.dumps({**config, "state_clip": "Infinity"}), "policy.state_clip must be a finite number in (0, 1000000]")]
    for text, expected in cases:
        (bad / "config.json").write_text(text.replace('"Infinity"', "Infinity"))
        for argv in (["eval", "--policy", bad], ["train", "--init", bad, "--run-dir", tmp_path / "never"]):
            line = assert_one_line_error(*run_cli(capsys, *argv)[::2], argv[0])
            assert "corrupt policy checkpoint" in line and expected in line, line
    assert not (tmp_path / "never").exists()


def test_a_policy_with_non_finite_weights_is_refused(capsys, workspace, tmp_path):
    from safetensors.torch import load_file, save_file

    bad = tmp_path / "nan-policy"
    shutil.copytree(workspace / "policy", bad)
    weights = load_file(str(bad / "model.safetensors"))
    next(iter(weights.values()))[0] = float("nan")
    save_file(weights, str(bad / "model.safetensors"))
    line = assert_one_line_error(*run_cli(capsys, "eval", "--policy", bad)[::2], "eval")
    assert "non-finite values" in line
    policy = tiny_policy()
    with torch.no_grad():
        next(policy.parameters()).fill_(float("inf"))
    with pytest.raises(ValueError, match="refusing to save a policy with non-finite values"):
        policy.save_pretrained(tmp_path / "never")
    assert not (tmp_path / "never").exists()


def test_a_failed_init_leaves_nothing_behind(capsys, tmp_path):
    other = FlowPolicy(FlowPolicyConfig(hidden_dim=32))
    other.save_pretrained(tmp_path / "other")
    line = assert_one_line_error(*run_cli(capsys, "train", "--init", tmp_path / "other", "--run-dir", tmp_path / "run",
                                          "--env.tasks", "reach-v3")[::2], "train")
    assert "other policy settings" in line and not (tmp_path / "run").exists()
    (tmp_path / "empty").mkdir()
    assert_one_line_error(*run_cli(capsys, "train", "--init", tmp_path / "other", "--run-dir", tmp_path / "empty",
                                   "--env.tasks", "reach-v3")[::2], "train")
    assert list((tmp_path / "empty").iterdir()) == []


def test_runs_never_overwrite_each_other(capsys, workspace, tmp_path):
    sft_run = tmp_path / "sft-run"
    sft_run.mkdir()
    (sft_run / "run.json").write_text('{"kind": "sft"}')
    (sft_run / "config.yaml").write_text("seed: 0\n")
    before = snapshot(sft_run)
    line = assert_one_line_error(*run_cli(capsys, "train", "--run-dir", sft_run)[::2], "train")
    assert f"already holds an SFT run: start RL from it with `stepnft train --config {sft_run}/config.yaml --init" in line
    line = assert_one_line_error(*run_cli(capsys, "sft", "--run-dir", workspace / "run")[::2], "sft")
    assert "already holds a training run: continue it with `stepnft train --resume" in line
    stray = tmp_path / "stray"
    stray.mkdir()
    (stray / "metrics.jsonl").write_text("{}\n")
    line = assert_one_line_error(*run_cli(capsys, "train", "--run-dir", stray)[::2], "train")
    assert "is not empty" in line
    assert snapshot(sft_run) == before and (stray / "metrics.jsonl").read_text() == "{}\n"


def test_demos_never_overwrite_other_demonstrations(capsys, tmp_path):
    demos = tmp_path / "demos"
    demos.mkdir()
    (demos / "manifest.json").write_text('{"format": "stepnft-demos", "version": 1, "tasks": ["push-v3"]}')
    line = assert_one_line_error(*run_cli(capsys, "demos", "--demos.path", demos, "--env.tasks", "reach-v3")[::2],
                                 "demos")
    assert "already holds demonstrations" in line
    assert "push-v3" in (demos / "manifest.json").read_text()


def test_a_full_disk_at_checkpoint_time_is_one_line_and_keeps_the_last_checkpoint(capsys, workspace, tmp_path,
                                                                                   monkeypatch):
    import errno

    import stepnft.checkpoint

    run = tmp_path / "run"
    shutil.copytree(workspace / "run", run)

    def disk_full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(stepnft.checkpoint, "save_file", disk_full)
    before = (run / "checkpoints" / "LATEST").read_text()
    with pytest.raises(OSError):
        save_checkpoint(run, 3, tiny_policy(), {"env_steps": 1})
    assert (run / "checkpoints" / "LATEST").read_text() == before
    assert not list((run / "checkpoints").glob(".tmp-*"))


def test_ray_workers_without_ray_installed_is_one_line(capsys, monkeypatch, tmp_path):
    import importlib.util

    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "ray" else find_spec(name, *a))
    line = assert_one_line_error(*run_cli(capsys, "train", "--run-dir", tmp_path / "run", "--ray.workers", 2)[::2],
                                 "train")
    assert 'needs Ray, which is not installed: pip install "stepnft[ray]"' in line
    assert not (tmp_path / "run").exists()
    code, out, _ = run_cli(capsys, "train", "--help")  # the options are listed all the same
    assert code == 0 and "--ray.workers" in out and "--ray.address" in out and "--ray.max-restarts" in out


def test_a_resumed_run_may_move_its_rollouts(capsys, workspace):
    """--resume takes the flags of TrainConfig.resumable (where a run computes), refuses any that
    would change what it computes, and names them."""
    from stepnft.config import TrainConfig

    assert TrainConfig.resumable == ("ray", "device", "gradient_checkpointing")
    cfg, resume = _config_from_argv(["--resume", str(workspace / "run"), "--ray.timeout-s", "30", "--device",
                                           "cpu", "--gradient-checkpointing"], "stepnft train", True)
    assert resume and cfg.ray.timeout_s == 30 and cfg.iterations == 2 and cfg.run_dir == str(workspace / "run")
    assert cfg.gradient_checkpointing  # recomputing activations changes memory, not the results
    cfg, _ = _config_from_argv(["--resume", str(workspace / "run"), "--seed", "0"], "stepnft train", True)
    assert cfg.seed == 0  # the run's own value: nothing changes
    for extra, dropped in [(["--ray.timeout-s", "30", "--seed", "3"], "drop: --seed"),
                           (["--algo.lr", "0.5", "--eval.episodes", "3"], "drop: --algo.lr --eval.episodes"),
                           (["--algo.name", "ppo"], "drop: --algo.name"),
                           (["--config", "configs/quickstart.yaml"], "drop: --config configs/quickstart.yaml")]:
        line = assert_one_line_error(*run_cli(capsys, "train", "--resume", workspace / "run", *extra)[::2], "train")
        assert ("takes no other flags than --ray.*, --device, --gradient-checkpointing, --iterations and "
                "--env-step-budget") in line or \
            "own config.yaml" in line
        assert dropped in line, line
    # Longer, never shorter; π-StepNFT's EMA schedule keeps the run's own horizon (2 iterations).
    cfg, _ = _config_from_argv(["--resume", str(workspace / "run"), "--iterations", "5", "--env-step-budget", "900"],
                               "stepnft train", True)
    assert (cfg.iterations, cfg.env_step_budget, cfg.algo.ema_horizon) == (5, 900, 2)
    line = assert_one_line_error(*run_cli(capsys, "train", "--resume", workspace / "run", "--iterations", "1")[::2],
                                 "train")
    assert "can lengthen a run, not shorten it: --iterations below the run's own (2 iterations" in line
    line = assert_one_line_error(*run_cli(capsys, "train", "--resume", workspace / "run", "--ray.timeout-s", "-1")[::2],
                                 "train")
    assert "--ray.timeout-s must be a finite number in (0, 604800], got -1.0" in line
