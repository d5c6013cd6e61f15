"""Interrupted commands resume or leave nothing; one writer per folder; a hand-edited config.yaml
is refused on --resume (README "Safety").

The chaos test starts real ``stepnft`` processes and stops each at seeded moments with SIGINT,
SIGTERM or SIGKILL, then checks what is left: nothing (no file but hidden ones), or a folder the
same command continues; then it reruns the command until it finishes and compares the artefacts
with an uninterrupted run's, byte for byte where the command promises it (demonstrations, the
trained policy of a resumed run, an evaluation's results).
"""

import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from stepnft.cli import main
from stepnft.runs import LOCK_NAME, RUN_FILES, writer_lock

pytestmark = pytest.mark.filterwarnings("ignore:Constant:UserWarning")

ENV = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), "PYTHONWARNINGS": "ignore"}
SMALL = ["--iterations", "4", "--episodes-per-iteration", "64", "--env.envs-per-task", "64", "--demos.episodes", "64",
         "--sft.steps", "40", "--eval.episodes", "16", "--eval.during-episodes", "16", "--algo.minibatch-size", "64",
         "--checkpoint-every", "1", "--num-threads", "1"]
DEMOS = ["demos", "--env.tasks", "reach-v3", "push-v3", "drawer-close-v3", "--demos.episodes", "8"]
SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGKILL)


def stepnft(*argv) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "stepnft.cli", *map(str, argv)], env=ENV, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def timed(*argv) -> float:
    """Seconds an uninterrupted ``stepnft argv`` takes (it must succeed): the window signals land in."""
    start = time.perf_counter()
    done = finish(*argv)
    assert done.returncode == 0, done.stderr[-2000:]
    return time.perf_counter() - start


def finish(*argv, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "stepnft.cli", *map(str, argv)], env=ENV, capture_output=True,
                          text=True, timeout=timeout)


def files(folder: Path) -> dict[str, bytes]:
    """The folder's files but hidden ones and TensorBoard's (whose names hold the time)."""
    if not folder.exists():
        return {}
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and not any(part.startswith(".") for part in p.relative_to(folder).parts)
            and "tb" not in p.relative_to(folder).parts}


def cleared_by_next_start(run: Path, sig: int) -> bool:
    """kill -9 gives no chance to clean up: what it left of a start before anything resumable
    is only the run's own files, which the next start of the same command removes (and says so)."""
    return sig == signal.SIGKILL and {p.name for p in run.iterdir() if not p.name.startswith(".")} <= RUN_FILES


def interrupt(argv: list, rng: random.Random, sig: int, latest: float) -> tuple[int, str]:
    """Start ``stepnft argv``, send ``sig`` after a seeded share (30-90 %) of ``latest`` seconds;
    (exit code, stderr)."""
    proc = stepnft(*argv)
    time.sleep(rng.uniform(0.3, 0.9) * latest)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=300)
    assert "Traceback" not in err, err[-3000:]
    return proc.returncode, err


@pytest.fixture(scope="module")
def bandit_yaml(tmp_path_factory):
    from stepnft.config import save_config
    from stepnft.demo_bandit import bandit_config

    path = tmp_path_factory.mktemp("chaos-config") / "bandit.yaml"
    save_config(bandit_config(), path)
    return path


def test_demos_interrupted_anywhere_continue_to_the_same_files(tmp_path):
    reference = tmp_path / "reference"
    duration = timed(*DEMOS, "--demos.path", reference)
    rng, stopped = random.Random(0), 0
    for k in range(6):
        out = tmp_path / f"demos{k}"
        code, err = interrupt([*DEMOS, "--demos.path", out], rng, SIGNALS[k % 3], duration)
        left = files(out)
        if code == 0 or (out / "manifest.json").is_file():  # finished before the signal (or as it exited)
            assert left == files(reference)
            continue
        stopped += 1
        # Stopped: resumable (a hidden record of the recording) or nothing at all.
        assert not left or (out / ".recording.json").is_file(), (code, err, sorted(left))
        if SIGNALS[k % 3] != signal.SIGKILL:
            # 130; -2 where the signal came as an import of a library ended (the interpreter then
            # exits by the signal), after the same one line.
            last = err.strip().splitlines()[-1]
            assert code in (130, -2) and last.startswith("stepnft demos: interrupted"), err[-1500:]
            assert ("rerun the same command to continue" in last) == (out / ".recording.json").is_file(), last
        done = finish(*DEMOS, "--demos.path", out)
        assert done.returncode == 0, done.stderr[-2000:]
        assert files(out) == files(reference), k  # bit-identical to the uninterrupted recording
        assert not (out / ".recording.json").exists() and not (out / LOCK_NAME).exists()
    assert stopped >= 3, "most signals must land while the command runs"


def test_demos_with_other_settings_than_an_interrupted_recording_are_one_line(capsys, tmp_path):
    out = tmp_path / "demos"
    proc = stepnft(*DEMOS, "--demos.path", out)
    deadline = time.time() + 120
    while not list(out.glob("*/.done.json")) and time.time() < deadline:  # a first task recorded whole
        time.sleep(0.1)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    before = files(out)
    assert main([*DEMOS[:-1], "9", "--demos.path", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "interrupted recording with other settings (episodes_per_task" in err, err
    assert files(out) == before


def test_train_interrupted_anywhere_resumes_to_the_same_policy(tmp_path, bandit_yaml):
    demos = tmp_path / "demos"
    ref = tmp_path / "reference"
    train = lambda run: ["train", "--config", bandit_yaml, "--run-dir", run, "--demos.path", demos, *SMALL]  # noqa: E731
    timed(*train(tmp_path / "warm"))  # the first run also records the demonstrations
    duration = timed(*train(ref))
    rng, stopped = random.Random(1), 0
    for k in range(6):
        run = tmp_path / f"run{k}"
        code, err = interrupt(train(run), rng, SIGNALS[k % 3], duration)
        stopped += code != 0
        if code != 0:
            resumable = (run / "checkpoints" / "LATEST").is_file()
            cleared = not resumable and bool(files(run)) and cleared_by_next_start(run, SIGNALS[k % 3])
            assert resumable or cleared or not files(run), (code, err[-1500:], sorted(files(run)))
            done = finish(*(["train", "--resume", run] if resumable else train(run)))
            assert done.returncode == 0, done.stderr[-2000:]
            assert not cleared or "removed an earlier start that was interrupted" in done.stderr
        for name in ("policy/model.safetensors", "best_policy/model.safetensors"):
            assert (run / name).read_bytes() == (ref / name).read_bytes(), (k, name)
        assert json.loads((run / "summary.json").read_text())["average"] == \
            json.loads((ref / "summary.json").read_text())["average"]
    assert stopped >= 3, "most signals must land while the command runs"


def test_sft_and_eval_interrupted_leave_nothing_or_their_finished_results(tmp_path, bandit_yaml):
    demos = tmp_path / "demos"
    sft = lambda run: ["sft", "--config", bandit_yaml, "--run-dir", run, "--demos.path", demos, *SMALL]  # noqa: E731
    timed(*sft(tmp_path / "warm"))  # the first run also records the demonstrations
    sft_time = timed(*sft(tmp_path / "reference"))
    policy = tmp_path / "reference" / "policy"
    evaluate = lambda out: ["eval", "--policy", policy, "--env.name", "bandit", "--env.tasks", "bandit",  # noqa: E731
                            "--env.max-episode-steps", "2", "--eval.episodes", "2000", "--out", out]
    eval_time = timed(*evaluate(tmp_path / "reference.json"))
    rng = random.Random(2)
    for k in range(4):
        run, out = tmp_path / f"sft{k}", tmp_path / f"eval{k}" / "eval.json"
        code, err = interrupt(sft(run), rng, SIGNALS[k % 3], sft_time)
        finished = (run / "summary.json").is_file()  # the signal came as it exited
        cleared = not finished and bool(files(run)) and cleared_by_next_start(run, SIGNALS[k % 3])
        assert finished or cleared or not files(run), (code, err[-1500:], sorted(files(run)))
        done = finish(*sft(run)) if not finished else None
        assert done is None or done.returncode == 0, done.stderr[-2000:]
        assert not cleared or "removed an earlier start that was interrupted" in done.stderr
        assert (run / "policy" / "model.safetensors").read_bytes() == (policy / "model.safetensors").read_bytes()
        code, err = interrupt(evaluate(out), rng, SIGNALS[k % 3], eval_time)
        if code == 0 or out.exists():  # finished: its results are whole
            assert out.read_bytes() == (tmp_path / "reference.json").read_bytes(), (code, err[-1500:])
        assert not (out.parent / ".eval.json.lock").exists() or SIGNALS[k % 3] == signal.SIGKILL
        assert finish(*evaluate(out)).returncode == 0
        assert out.read_bytes() == (tmp_path / "reference.json").read_bytes()


# --- one writer per folder ---------------------------------------------------------------------
HOLD = "import sys, time\nfrom stepnft.runs import writer_lock\nwith writer_lock(sys.argv[1]):\n" \
       "    print('held', flush=True)\n    time.sleep(120)\n"


def test_a_second_writer_is_one_line_naming_the_holder_and_kill_9_frees_the_folder(capsys, tmp_path, bandit_yaml):
    folder = tmp_path / "busy"
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(folder)], env=ENV, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        for argv in (["demos", "--env.tasks", "reach-v3", "--demos.path", folder],
                     ["train", "--config", bandit_yaml, "--run-dir", folder, "--demos.path", tmp_path / "d", *SMALL],
                     ["sft", "--config", bandit_yaml, "--run-dir", folder, "--demos.path", tmp_path / "d", *SMALL],
                     ["compare", "--config", bandit_yaml, "--algos", "stepnft", "--out", folder]):
            assert main([str(a) for a in argv]) == 2, argv
            err = capsys.readouterr().err.strip().splitlines()[-1]
            assert f"is being written by another stepnft process (PID {holder.pid})" in err, (argv, err)
        assert [p.name for p in folder.iterdir()] == [LOCK_NAME]  # nothing written beside the holder's lock
    finally:
        holder.kill()  # kill -9: the lock ends with its process, no stale lock to clean by hand
        holder.wait()
    with writer_lock(folder) as lock:
        assert lock.read_text() == str(os.getpid())
    assert list(folder.iterdir()) == []  # the dead holder's lock file taken over, then removed


def test_the_eval_output_has_one_writer(capsys, tmp_path):
    from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig

    FlowPolicy(FlowPolicyConfig(state_dim=2, action_dim=2, lang_dim=0, hidden_dim=16, num_layers=1,
                                horizon=2, n_exec=2)).save_pretrained(tmp_path / "policy")
    out = tmp_path / "results" / "eval.json"
    out.parent.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", HOLD.replace("writer_lock(sys.argv[1])",
                                                                  "writer_lock(sys.argv[1], '.eval.json.lock')"),
                               str(out.parent)], env=ENV, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        code = main(["eval", "--policy", str(tmp_path / "policy"), "--env.name", "bandit", "--env.tasks", "bandit",
                     "--env.max-episode-steps", "2", "--eval.episodes", "4", "--out", str(out)])
        assert code == 2 and f"PID {holder.pid}" in capsys.readouterr().err and not out.exists()
    finally:
        holder.kill()
        holder.wait()


# --- the saved config and the checkpoint agree -------------------------------------------------
def test_resume_refuses_a_hand_edited_config_in_one_line_and_resumes_once_restored(capsys, tmp_path, bandit_yaml):
    run = tmp_path / "run"
    argv = ["train", "--config", bandit_yaml, "--run-dir", run, "--demos.path", tmp_path / "demos", *SMALL]
    argv[argv.index("--iterations") + 1] = "2"
    assert main([str(a) for a in argv]) == 0
    capsys.readouterr()
    saved = (run / "config.yaml").read_text()
    (run / "config.yaml").write_text(saved.replace("lr: 0.0003", "lr: 0.003").replace("beta: 1.0", "beta: 2.0"))
    assert (run / "config.yaml").read_text() != saved, "the edit must change the file"
    before = {p: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    assert main(["train", "--resume", str(run), "--iterations", "3"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    line = [e for e in err if ": error: " in e]
    assert len(line) == 1 and "config.yaml was edited after checkpoint iter_000002 was written (algo." in line[0], err
    assert f"`stepnft train --config {run}/config.yaml --run-dir NEW_DIR`" in line[0]
    assert {p: p.read_bytes() for p in run.rglob("*") if p.is_file()} == before  # nothing written
    (run / "config.yaml").write_text(saved)
    assert main(["train", "--resume", str(run), "--iterations", "3"]) == 0


@pytest.mark.parametrize("raised", [
    __import__("ctypes").ArgumentError("argument 1: KeyboardInterrupt: "),  # a signal while MuJoCo's EGL loads
    RuntimeError("import failed"),
])
def test_ctrl_c_wrapped_by_a_foreign_call_is_the_interrupted_line(capsys, monkeypatch, raised):
    """A Ctrl-C that ctypes turned into ArgumentError (or that another error chains) ends as an
    interruption (exit 130, one line), not a traceback."""
    import stepnft.cli as cli

    if isinstance(raised, RuntimeError):
        raised.__context__ = KeyboardInterrupt()

    def handler(argv):
        raise raised

    monkeypatch.setitem(cli.HANDLERS, "demos", handler)
    assert main(["demos"]) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("stepnft demos: "), err
