"""A camera policy end to end on a tiny budget: demonstrations with images -> SFT with random
shifts -> π-StepNFT on rendered observations -> evaluation, videos of what the policy saw, and
the suites through ``stepnft eval``."""

import json

import numpy as np
import pytest

from stepnft.cli import main
from stepnft.data.demos import generate_demos
from stepnft.envs.base import RenderingError
from stepnft.policies.base import load_policy
from stepnft.runs import read_metrics

pytestmark = pytest.mark.filterwarnings("ignore:Constant:UserWarning")

CAMERA = ["--env.cameras", "corner", "--env.image-size", "16", "--env.state-obs", "proprio"]


@pytest.fixture(scope="module")
def camera_demos(tmp_path_factory):
    try:
        return generate_demos("reach-v3", episodes=1, out_dir=tmp_path_factory.mktemp("demos") / "cam",
                              progress=False, cameras=["corner"], image_size=16, simulator="metaworld")
    except RenderingError as err:
        pytest.skip(f"no offscreen rendering here (EGL): {err}")


def test_a_camera_policy_trains_end_to_end(tmp_path, camera_demos):
    run = tmp_path / "run"
    args = ["train", "--run-dir", str(run), "--demos.path", str(camera_demos), "--demos.episodes", "1",
            "--iterations", "2", "--episodes-per-iteration", "2", "--env.tasks", "reach-v3", "--env.envs-per-task", "2",
            "--env.max-episode-steps", "16", *CAMERA, "--policy.state-dim", "4", "--policy.cameras", "corner",
            "--policy.image-size", "16", "--policy.image-channels", "4", "--policy.hidden-dim", "32",
            "--sft.steps", "10", "--sft.batch-size", "16", "--algo.minibatch-size", "16", "--eval.episodes", "2",
            "--eval.every", "0", "--eval.videos", "1", "--env.randomize", "lighting,friction"]
    assert main(args) == 0
    policy = load_policy(run / "policy")
    assert policy.config.cameras == ["corner"] and policy.config.state_dim == 4
    records = read_metrics(run / "metrics.jsonl")
    assert [r["iteration"] for r in records if "losses/E_pos" in r] == [1, 2]
    assert all(np.isfinite(r["losses/E_pos"]) for r in records if "losses/E_pos" in r)
    assert json.loads((run / "summary.json").read_text())["tasks"]["reach-v3"]["after"]["episodes"] == 2

    import imageio.v3 as iio

    (video,) = (run / "videos").glob("reach-v3_ep0_*.mp4")
    frame = next(iter(iio.imiter(video)))
    assert frame.shape[0] == 224 and frame.shape[1] > 224  # the scene, and what the policy saw beside it
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(run / "tb")).Reload()
    assert any(tag.startswith("videos/reach-v3_ep0") for tag in events.Tags()["images"])

    out = tmp_path / "suites.json"
    assert main(["eval", "--policy", str(run / "policy"), "--env.tasks", "reach-v3", "--env.envs-per-task", "2",
                 "--env.max-episode-steps", "8", "--env.image-size", "16", "--eval.episodes", "2",
                 "--suite", "ind,vision", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    vision = result["suites"]["vision"]
    assert vision["tasks"]["reach-v3"]["episodes"] == 2 and set(vision["breakdown"]) == {"table_color", "floor_color"}
    assert result["ood_average"] == vision["average"]
