"""Saved files that were damaged, and folders that cannot take what a command writes: every case
is one line, exit 2, no traceback, and nothing of the input is changed (README "Safety").

Policies: truncated or empty safetensors, weights of other shapes, a config.json of the wrong
kind. Checkpoints: a truncated state, a state.json of the wrong kind, LATEST outside the run.
Folders: a symlinked run folder (followed: it is the user's own), a read-only filesystem and a
full small one (both real tmpfs mounts, where this process may mount; CI runs as root).
"""

import dataclasses
import json
import os
import shutil
import subprocess
import uuid
from pathlib import Path

import pytest
import torch

from stepnft.checkpoint import save_checkpoint
from stepnft.cli import main
from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig

pytestmark = pytest.mark.filterwarnings("ignore:Constant:UserWarning")

BANDIT = ["--env.name", "bandit", "--env.tasks", "bandit", "--env.max-episode-steps", "2", "--eval.episodes", "4"]


def bandit_policy(hidden: int = 16) -> FlowPolicy:
    torch.manual_seed(0)
    return FlowPolicy(FlowPolicyConfig(state_dim=2, action_dim=2, lang_dim=0, hidden_dim=hidden, num_layers=1,
                                       horizon=2, n_exec=2))


def files(folder: Path) -> dict:
    return {p: p.read_bytes() for p in sorted(Path(folder).rglob("*")) if p.is_file()}


def one_line(capsys, *argv) -> str:
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if ": error: " in line]
    assert code == 2 and "Traceback" not in err and len(lines) == 1, (code, err[-2000:])
    return lines[0]


def truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 2])


def empty(path: Path) -> None:
    path.write_bytes(b"")


def other_shapes(path: Path) -> None:
    bandit_policy(hidden=32).save_pretrained(path.parent / "wider")
    shutil.copy(path.parent / "wider" / "model.safetensors", path)
    shutil.rmtree(path.parent / "wider")


def garbage(path: Path) -> None:
    path.write_bytes(os.urandom(256))


POLICY_DAMAGE = {
    "model.safetensors truncated": ("model.safetensors", truncate),
    "model.safetensors empty": ("model.safetensors", empty),
    "model.safetensors of other shapes": ("model.safetensors", other_shapes),
    "model.safetensors random bytes": ("model.safetensors", garbage),
    "processor.safetensors truncated": ("processor.safetensors", truncate),
    "config.json a string": ("config.json", lambda p: p.write_text('"flow"')),
    "config.json type a number": ("config.json", lambda p: p.write_text(json.dumps({"type": 3}))),
    "config.json a width as text": ("config.json", lambda p: p.write_text(json.dumps(
        {**json.loads(p.read_text()), "hidden_dim": "wide"}))),
    "config.json truncated": ("config.json", truncate),
    "config.json not UTF-8": ("config.json", lambda p: p.write_bytes(b"\xff\xfe{")),
}


@pytest.mark.parametrize("case", POLICY_DAMAGE)
def test_a_damaged_policy_folder_is_one_line_for_eval_and_train_init(capsys, tmp_path, case):
    name, damage = POLICY_DAMAGE[case]
    policy = tmp_path / "policy"
    bandit_policy().save_pretrained(policy)
    damage(policy / name)
    before = files(policy)
    line = one_line(capsys, "eval", "--policy", policy, *BANDIT)
    assert str(policy) in line or name in line, line
    one_line(capsys, "train", "--init", policy, "--run-dir", tmp_path / "never", *BANDIT)
    assert files(policy) == before and not (tmp_path / "never").exists()


def resumable_run(root: Path) -> Path:
    """A bandit training run's folder with two checkpoints (as `stepnft train` leaves it)."""
    from stepnft.config import save_config
    from stepnft.demo_bandit import bandit_config

    run = root / "run"
    run.mkdir(parents=True)
    (run / "run.json").write_text('{"kind": "train"}')
    cfg = bandit_config()
    save_config(dataclasses.replace(cfg, run_dir=str(run), demos=dataclasses.replace(cfg.demos, path=str(root / "demos"))),
                run / "config.yaml")
    for it in (1, 2):
        save_checkpoint(run, it, bandit_policy(), {"env_steps": it, "torch_rng": torch.get_rng_state()})
    return run


CHECKPOINT_DAMAGE = {
    "state.safetensors truncated": lambda ck: truncate(ck / "state.safetensors"),
    "state.json a list": lambda ck: (ck / "state.json").write_text("[]"),
    "state.json truncated": lambda ck: truncate(ck / "state.json"),
    "state.json without its state": lambda ck: (ck / "state.json").write_text(json.dumps({"format_version": 1})),
    "policy weights truncated": lambda ck: truncate(ck / "policy" / "model.safetensors"),
    "LATEST outside the run": lambda ck: (ck.parent / "LATEST").write_text("../../elsewhere/iter_000002"),
    "LATEST empty": lambda ck: (ck.parent / "LATEST").write_text(""),
    "LATEST binary": lambda ck: (ck.parent / "LATEST").write_bytes(b"\x00\xff\x00"),
}


@pytest.mark.parametrize("case", CHECKPOINT_DAMAGE)
def test_a_damaged_checkpoint_is_one_line_on_resume_and_says_how_to_go_on(capsys, tmp_path, case):
    run = resumable_run(tmp_path)
    CHECKPOINT_DAMAGE[case](run / "checkpoints" / "iter_000002")
    before = files(run)
    line = one_line(capsys, "train", "--resume", run)
    assert "checkpoint" in line or "LATEST" in line, line
    assert files(run) == before


def test_a_symlinked_run_folder_is_followed_and_its_lock_and_checks_hold(capsys, tmp_path):
    run = resumable_run(tmp_path / "real")
    link = tmp_path / "link"
    link.symlink_to(run, target_is_directory=True)
    # The link is the user's name for the folder: a new run there is refused as the folder is.
    line = one_line(capsys, "train", "--config", run / "config.yaml", "--run-dir", link)
    assert f"{link} already holds a training run: continue it with `stepnft train --resume {link}`" in line
    (run / "config.yaml").write_text((run / "config.yaml").read_text().replace("seed: 0", "seed: 5"))
    save_checkpoint(run, 3, bandit_policy(), {"env_steps": 3, "torch_rng": torch.get_rng_state()},
                    config={"seed": 0})
    assert "config.yaml was edited after checkpoint iter_000003" in one_line(capsys, "train", "--resume", link)
    assert link.is_symlink() and run.is_dir()


# --- folders that cannot take what a command writes ----------------------------------------------
@pytest.fixture
def small_mount(tmp_path):
    """A real 512 KiB tmpfs at a fresh folder (``mount`` needs root); unmounted after the test."""
    point = tmp_path / f"mnt-{uuid.uuid4().hex[:6]}"
    point.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=512k", "tmpfs", str(point)], capture_output=True).returncode:
        pytest.skip("cannot mount a tmpfs here (needs root): the full and read-only filesystem cases need one")
    try:
        yield point
    finally:
        subprocess.run(["umount", "-l", str(point)], check=False)


def test_a_full_small_filesystem_is_one_line_and_leaves_no_half_written_file(capsys, tmp_path, small_mount):
    fd = os.open(small_mount / "filler", os.O_WRONLY | os.O_CREAT)
    try:  # full to the last block
        while os.write(fd, b"\0" * 4096):
            pass
    except OSError:
        pass
    finally:
        os.close(fd)
    out = small_mount / "demos"
    line = one_line(capsys, "demos", "--env.tasks", "reach-v3", "--demos.episodes", "3", "--demos.path", out)
    assert "No space left on device" in line or "space" in line, line
    assert not out.exists() and [p.name for p in small_mount.iterdir()] == ["filler"]
    policy = tmp_path / "policy"
    bandit_policy().save_pretrained(policy)
    line = one_line(capsys, "eval", "--policy", policy, *BANDIT, "--out", small_mount / "results" / "eval.json")
    assert "space" in line or "No space" in line, line


def test_a_read_only_filesystem_is_one_line_before_any_work(capsys, tmp_path, small_mount):
    run = resumable_run(small_mount)
    subprocess.run(["mount", "-o", "remount,ro", str(small_mount)], check=True)
    before = files(run)
    for argv in (["train", "--resume", run], ["demos", "--env.tasks", "reach-v3", "--demos.path", small_mount / "d"],
                 ["train", "--config", run / "config.yaml", "--run-dir", small_mount / "new"]):
        line = one_line(capsys, *argv)
        assert "Read-only file system" in line or "cannot write" in line, (argv, line)
    assert files(run) == before
