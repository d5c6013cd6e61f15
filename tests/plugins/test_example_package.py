"""The worked plugin package under examples/ (its own pyproject.toml): pip installs it, and a
fresh stepnft process finds its simulator, policy type and algorithm variant by entry point and
fine-tunes with all three, resumes and evaluates; nothing in stepnft names the package."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "stepnft-example-plugin"


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """The example installed by pip (from a copy, so its build files stay out of the repository)."""
    work = tmp_path_factory.mktemp("example")
    source = shutil.copytree(EXAMPLE, work / "src", ignore=shutil.ignore_patterns("runs", "demos", "build", "*.egg-info"))
    done = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
                           "--target", str(work / "site"), str(source)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    return work / "site"


def stepnft(site: Path, cwd: Path, *argv) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")]),
           "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    return subprocess.run([sys.executable, "-m", "stepnft.cli", *map(str, argv)], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=900)


def test_stepnft_names_no_example_part():
    package = Path(__file__).resolve().parents[2] / "stepnft"
    for path in package.rglob("*.py"):
        text = path.read_text()
        assert "stepnft_example" not in text and "residual_flow" not in text, path


def test_the_installed_example_fine_tunes_resumes_and_evaluates(site, tmp_path):
    config = yaml.safe_load((EXAMPLE / "reacher.yaml").read_text())
    config.update(iterations=3, episodes_per_iteration=32)
    config["env"]["envs_per_task"] = 8
    config["demos"]["episodes"] = 4
    config["eval"].update(episodes=16, every=2, during_episodes=8)
    config["sft"] = {"steps": 200}
    (tmp_path / "reacher.yaml").write_text(yaml.safe_dump(config))
    done = stepnft(site, tmp_path, "train", "--config", "reacher.yaml")
    assert done.returncode == 0, done.stderr[-3000:]
    run = tmp_path / "runs" / "reacher"
    saved = yaml.safe_load((run / "config.yaml").read_text())
    assert saved["env"]["name"] == "reacher" and saved["algo"]["name"] == "stepnft-warmup"
    assert saved["policy"]["type"] == "residual_flow" and saved["policy"]["blocks"] == 2
    policy = json.loads((run / "policy" / "config.json").read_text())
    assert policy["type"] == "residual_flow" and policy["blocks"] == 2
    lr = [row["charts/learning_rate"] for row in map(json.loads, (run / "metrics.jsonl").read_text().splitlines())
          if "charts/learning_rate" in row]
    assert lr == pytest.approx([1e-4 * k / 5 for k in (1, 2, 3)])  # the warm-up, 5 iterations long
    again = stepnft(site, tmp_path, "train", "--resume", run, "--iterations", 4)
    assert again.returncode == 0, again.stderr[-3000:]
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["charts/learning_rate"] for r in rows if "charts/learning_rate" in r][-1] == pytest.approx(1e-4 * 4 / 5)
    evaluated = stepnft(site, tmp_path, "eval", "--policy", run / "policy", "--env.name", "reacher",
                        "--env.tasks", "reach", "--env.max-episode-steps", 50, "--eval.episodes", 8,
                        "--out", tmp_path / "eval.json")
    assert evaluated.returncode == 0, evaluated.stderr[-3000:]
    assert 0.0 <= json.loads((tmp_path / "eval.json").read_text())["average"] <= 1.0


def test_the_example_simulator_keeps_the_chunk_env_contract(site, monkeypatch):
    monkeypatch.syspath_prepend(str(site))
    from stepnft.envs.rendering import check_gl_platform
    from stepnft_example.sim import INFO, Reacher, ReacherExpert

    assert INFO.opengl
    check_gl_platform(renders=False)  # as stepnft.envs.get_simulator does first for such a simulator

    sim = Reacher()
    env = sim.make_env("reach", n_exec=4, max_episode_steps=50, seed=3)
    first, _ = env.reset(seed=7)
    env.step(np.zeros((4, 2)))
    again, _ = env.reset(seed=7)
    np.testing.assert_array_equal(first["state"], again["state"])  # a seeded reset depends on the seed only
    state = env.np_random.bit_generator.state
    obs, info = env.reset(options={"idle": True})
    assert info["episode_steps"] == 0 and env.np_random.bit_generator.state == state
    assert env.step(np.zeros((4, 2)))[3] and env.step(np.zeros((4, 2)))[4]["steps"] == 0  # ended: a no-op
    wins = 0
    for seed in range(20):
        expert, (obs, _) = ReacherExpert(seed), env.reset(seed=seed)
        for _ in range(50):
            obs, _, terminated, truncated, info = env.step(np.stack([expert.act(obs)] * 4))
            if terminated or truncated:
                break
        wins += info["success"]
    assert wins >= 17  # the scripted expert reaches the target (open loop within a chunk: not always)
