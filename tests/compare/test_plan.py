"""What a comparison runs: the command's flags (those quoted in result folders keep working),
its overrides applied through the run config's own fields and checks, the jobs."""

import dataclasses
import shlex
from pathlib import Path

import pytest

from stepnft.cli import _parse
from stepnft.compare import CompareCommand, command_line, comparison_config, plan
from stepnft.demo_bandit import bandit_config

ROOT = Path(__file__).resolve().parents[2]


def quoted_commands() -> list[str]:
    """The one-line ``stepnft compare`` commands of the comparisons in benchmarks/results."""
    lines = [line.strip() for path in sorted((ROOT / "benchmarks" / "results").glob("compare*/*.md"))
             for line in path.read_text().splitlines()]
    return sorted({line for line in lines if line.startswith("stepnft compare --") and not line.endswith("\\")})


def test_result_folders_quote_commands():
    assert len(quoted_commands()) >= 3  # else the next test checks nothing


EVERY_FLAG = ("stepnft compare --config c.yaml --algos stepnft,ppo --seeds 0 1 --tasks reach-v3 push-v3 --env-steps 9 "
              "--eval-episodes 3 --suites ind,vision --suite-episodes 5 --jobs 2 --out o")


@pytest.mark.parametrize("line", [*quoted_commands(), EVERY_FLAG])
def test_the_commands_quoted_in_result_folders_still_parse_to_themselves(line):
    """A folder's report shows the command that resumes it: --env-steps, --eval-episodes,
    --tasks, --suites, --suite-episodes, --jobs and --out must keep their meaning."""
    cmd = _parse(CompareCommand, shlex.split(line)[2:], CompareCommand(), "stepnft compare")
    jobs = f" --jobs {cmd.jobs}" if cmd.jobs else ""
    assert command_line(cmd) == line.replace(jobs, "")


def test_flags_take_space_or_comma_separated_names():
    cmd = CompareCommand(algos=["stepnft,ppo", "stepnft"], tasks=["reach-v3, push-v3"], suites=["ind,vision"])
    assert cmd.algos == ["stepnft", "ppo"] and cmd.tasks == ["reach-v3", "push-v3"] and cmd.suites == ["ind", "vision"]
    assert CompareCommand(tasks=[]).tasks is None  # the base config's
    with pytest.raises(ValueError, match="--algos nope"):
        CompareCommand(algos=["stepnft,nope"])


def test_overrides_are_set_on_the_config_fields_and_checked_there():
    base = bandit_config(iterations=3, episodes_per_iteration=100)
    cfg = comparison_config(base, CompareCommand(tasks=["bandit"], env_steps=1000, eval_episodes=7))
    assert cfg.env.tasks == ["bandit"] and cfg.env_step_budget == 1000 and cfg.eval.episodes == 7
    assert cfg.iterations == 10 and cfg.num_threads == 1 and cfg.init is None  # the budget binds
    assert cfg.eval == dataclasses.replace(base.eval, episodes=7) and cfg.algo == base.algo
    unchanged = comparison_config(dataclasses.replace(base, env_step_budget=500), CompareCommand())
    assert unchanged.env == base.env and unchanged.eval == base.eval and unchanged.env_step_budget == 500

    # The sections' own checks, with the flags named.
    with pytest.raises(ValueError, match=r"env_step_budget must be an integer in \[1, 1000000000000\].*--env-steps"):
        comparison_config(base, CompareCommand(env_steps=0))
    with pytest.raises(ValueError, match="validation and test states must not overlap"):
        comparison_config(base, CompareCommand(env_steps=10, eval_episodes=2_000_000))
    with pytest.raises(ValueError, match="unknown bandit task 'reach-v3'"):
        comparison_config(base, CompareCommand(env_steps=10, tasks=["reach-v3"]))
    # What a comparison needs beyond a valid run config.
    with pytest.raises(ValueError, match="needs one env-step budget"):
        comparison_config(base, CompareCommand())
    with pytest.raises(ValueError, match="evaluates every run"):
        comparison_config(base, CompareCommand(env_steps=10, eval_episodes=0))


def test_a_relative_out_folder_gives_relative_paths_in_the_saved_configs(tmp_path, monkeypatch):
    from stepnft.config import save_config

    save_config(bandit_config(iterations=4, episodes_per_iteration=10), tmp_path / "base.yaml")
    monkeypatch.chdir(tmp_path)
    sft_jobs, run_jobs, out = plan(CompareCommand(config="base.yaml", algos=["stepnft", "ppo"], seeds=[0, 1],
                                                  env_steps=100, out="cmp"))
    assert str(out) == "cmp" and (tmp_path / "cmp" / "compare.json").is_file()
    assert [j.name for j in sft_jobs] == ["sft_seed0", "sft_seed1"]
    assert [j.name for j in run_jobs] == ["stepnft_seed0", "ppo_seed0", "stepnft_seed1", "ppo_seed1"]
    assert sft_jobs[1].config.run_dir == "cmp/sft/seed1" and sft_jobs[1].config.demos.path == "cmp/demos/seed1"
    assert run_jobs[2].config.init == "cmp/sft/seed1/policy" and run_jobs[2].config.seed == 1
    assert run_jobs[0].config.iterations == 10 and run_jobs[0].config.env_step_budget == 100
    assert run_jobs[0].config.algo.ema_horizon == 4  # the base config's iterations, not the budget's


def test_an_init_policy_in_the_base_config_is_every_seeds_sft_start(tmp_path, monkeypatch):
    """A LeRobot VLA enters a comparison as the base config's ``init`` (a new SmolVLA folder):
    every seed's SFT fine-tunes it, every RL run starts from its seed's SFT policy."""
    import json

    from stepnft.config import save_config

    save_config(dataclasses.replace(bandit_config(iterations=4, episodes_per_iteration=10), init="models/vla"),
                tmp_path / "base.yaml")
    monkeypatch.chdir(tmp_path)
    sft_jobs, run_jobs, out = plan(CompareCommand(config="base.yaml", algos=["stepnft", "ppo"], seeds=[0, 1],
                                                  env_steps=100, out="cmp"))
    assert [j.config.init for j in sft_jobs] == ["models/vla", "models/vla"]
    assert [j.config.init for j in run_jobs] == ["cmp/sft/seed0/policy"] * 2 + ["cmp/sft/seed1/policy"] * 2
    assert json.loads((tmp_path / "cmp" / "compare.json").read_text())["init"] == "models/vla"  # a shared setting


def test_a_setting_added_since_a_comparison_was_recorded_resumes_at_its_default(tmp_path):
    import json

    from stepnft.compare.plan import check_same_settings

    recorded = {"algo": {"lr": 1e-4}, "seed_free": 1}
    path = tmp_path / "compare.json"
    path.write_text(json.dumps(recorded))
    defaults = {"algo": {"lr": 3e-4, "mean_correction": True}, "seed_free": 1}
    check_same_settings(path, {"algo": {"lr": 1e-4, "mean_correction": True}, "seed_free": 1}, defaults)
    with pytest.raises(ValueError, match="differs in: algo.mean_correction"):  # the new setting changed
        check_same_settings(path, {"algo": {"lr": 1e-4, "mean_correction": False}, "seed_free": 1}, defaults)
    with pytest.raises(ValueError, match="differs in: algo.lr"):  # a recorded one changed
        check_same_settings(path, {"algo": {"lr": 2e-4, "mean_correction": True}, "seed_free": 1}, defaults)


def test_variant_set_tunes_one_variant_and_is_held_once_its_runs_exist(tmp_path, monkeypatch):
    import json

    from stepnft.config import save_config

    save_config(bandit_config(iterations=4, episodes_per_iteration=10), tmp_path / "base.yaml")
    monkeypatch.chdir(tmp_path)

    def cmd(*variant_set, algos=("stepnft", "ppo", "beta-0.5")):
        return CompareCommand(config="base.yaml", algos=list(algos), env_steps=100, out="cmp",
                              variant_set=list(variant_set))

    _, runs, _ = plan(cmd("ppo.lr=3e-5", "ppo.clip_coef=0.3", "beta-0.5.kl_beta=0.01"))
    algo = {j.name: j.config.algo for j in runs}
    assert algo["ppo_seed0"].lr == 3e-5 and algo["ppo_seed0"].clip_coef == 0.3 and algo["ppo_seed0"].name == "ppo"
    assert algo["stepnft_seed0"].lr != 3e-5 and algo["beta-0.5_seed0"].beta == 0.5  # the variant's own kept
    assert algo["beta-0.5_seed0"].kl_beta == 0.01  # a name with a dot: the longest variant that prefixes the key
    assert json.loads((tmp_path / "cmp" / "compare.json").read_text())["variant_set"]["ppo"] == \
        {"lr": 3e-5, "clip_coef": 0.3}
    assert "--variant-set ppo.lr=3e-5 ppo.clip_coef=0.3 beta-0.5.kl_beta=0.01 --out cmp" in command_line(
        cmd("ppo.lr=3e-5", "ppo.clip_coef=0.3", "beta-0.5.kl_beta=0.01"))
    plan(cmd("ppo.lr=1e-5"))  # no ppo run folder yet: its settings may still change
    (tmp_path / "cmp" / "runs" / "ppo").mkdir(parents=True)
    with pytest.raises(ValueError, match=r"ran ppo with other --variant-set settings .*delete cmp/runs/ppo"):
        plan(cmd("ppo.lr=3e-5"))
    plan(cmd("ppo.lr=1e-5"))  # the same: resumes
    plan(cmd(algos=("stepnft",)))  # a rerun of other variants keeps ppo's record
    assert json.loads((tmp_path / "cmp" / "compare.json").read_text())["variant_set"]["ppo"] == {"lr": 1e-5}
    for bad, match in [("ppo.lr", "expected VARIANT.FIELD=VALUE"), ("nope.lr=1", "expected VARIANT.FIELD=VALUE"),
                       ("grpo.lr=1e-5", "grpo is not among --algos"), ("ppo.name=grpo", "algorithm is its own")]:
        with pytest.raises(ValueError, match=match):
            cmd(bad)
    with pytest.raises(ValueError, match="--variant-set ppo: .*unknown config key 'algo.nope'"):
        plan(CompareCommand(config="base.yaml", algos=["ppo"], env_steps=100, out="cmp2", variant_set=["ppo.nope=1"]))
    with pytest.raises(ValueError, match="--variant-set ppo: .*lr"):
        plan(CompareCommand(config="base.yaml", algos=["ppo"], env_steps=100, out="cmp3", variant_set=["ppo.lr=-1"]))


def test_the_report_states_the_variant_settings():
    from stepnft.compare.report import comparison_markdown

    cmd = CompareCommand(algos=["stepnft", "ppo"], env_steps=100, variant_set=["ppo.lr=3e-5"])
    text = comparison_markdown(cmd, {"columns": ["average"], "reference": "stepnft", "rows": {}},
                               {"env_step_budget": 100, "eval": {"episodes": 5}}, {})
    assert "--variant-set ppo.lr=3e-5" in text and "(`--variant-set`): ppo: lr=3e-05." in text
