"""The image side of policies: image preparation, random-shift augmentation, the CNN encoder,
camera flow policies saved and loaded, and instruction variants in the processor."""

import json

import pytest
import torch

from stepnft.policies.base import Policy
from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig
from stepnft.policies.processor import ObservationProcessor
from stepnft.policies.vision import ImageEncoder, prepare_images, random_shift


def test_prepare_images_scales_and_resizes():
    images = torch.randint(0, 256, (2, 3, 3, 32, 32), dtype=torch.uint8)
    images[0, 0] = 0
    images[0, 1] = 255
    out = prepare_images(images, 32)
    assert out.dtype == torch.float32 and out.shape == (2, 3, 3, 32, 32)
    assert out[0, 0].eq(-1).all() and out[0, 1].eq(1).all()
    small = prepare_images(images, 16)  # area resampling: 2x2 blocks averaged
    torch.testing.assert_close(small[1, 2, :, 0, 0], out[1, 2, :, :2, :2].mean(dim=(1, 2)))
    with pytest.raises(ValueError, match="uint8"):
        prepare_images(images.float(), 16)


def test_random_shift_translates_each_image_by_its_own_offset():
    images = torch.arange(2 * 1 * 1 * 8 * 8, dtype=torch.float32).view(2, 1, 1, 8, 8)
    assert random_shift(images, 0) is images
    out = random_shift(images, 2, torch.Generator().manual_seed(0))
    assert out.shape == images.shape
    padded = torch.nn.functional.pad(images.flatten(0, 1), (2, 2, 2, 2), mode="replicate")
    dy, dx = torch.randint(0, 5, (2, 2), generator=torch.Generator().manual_seed(0))
    for i in range(2):  # the same generator draws give the offsets: out is that crop of the padded image
        torch.testing.assert_close(out[i, 0], padded[i, :, dy[i]:dy[i] + 8, dx[i]:dx[i] + 8])
    torch.testing.assert_close(random_shift(images, 2, torch.Generator().manual_seed(0)), out)


def test_image_encoder_fuses_views_in_order():
    encoder = ImageEncoder(views=2, size=16, channels=8, features=5)
    x = torch.randn(3, 2, 3, 16, 16)
    out = encoder(x)
    assert out.shape == (3, 10) and encoder.out_dim == 10
    swapped = encoder(x.flip(1))
    torch.testing.assert_close(swapped, torch.cat([out[:, 5:], out[:, :5]], dim=1))  # shared weights, view order kept
    with pytest.raises(ValueError, match="2 camera views"):
        encoder(x[:, :1])


def test_camera_policy_round_trip_and_old_configs(tmp_path):
    cfg = FlowPolicyConfig(state_dim=4, lang_dim=0, hidden_dim=16, cameras=["corner", "topview"], image_size=16,
                           image_channels=4, image_features=8)
    policy = FlowPolicy(cfg)
    raw = {"state": torch.randn(3, 4), "task": torch.zeros(3, dtype=torch.int64),
           "image": torch.randint(0, 256, (3, 2, 3, 32, 32), dtype=torch.uint8)}
    obs = policy.processor(raw)
    assert obs["image"].shape == (3, 2, 3, 16, 16)  # resized by the processor, outside the network
    policy.save_pretrained(tmp_path / "camera")
    loaded = Policy.from_pretrained(tmp_path / "camera")
    assert loaded.config == cfg
    x, t = torch.randn(3, 4, 4), torch.rand(3)
    torch.testing.assert_close(loaded.velocity(loaded.processor(raw), x, t), policy.velocity(obs, x, t))
    other = raw | {"image": raw["image"].flip(-1)}
    assert not torch.allclose(policy.velocity(policy.processor(other), x, t), policy.velocity(obs, x, t))
    with pytest.raises(ValueError, match="env.cameras"):
        policy.processor({"state": raw["state"], "task": raw["task"]})
    # A config.json written before camera policies existed loads as the state policy it was.
    state = FlowPolicy(FlowPolicyConfig(state_dim=4, lang_dim=0, hidden_dim=16))
    state.save_pretrained(tmp_path / "old")
    saved = json.loads((tmp_path / "old" / "config.json").read_text())
    for key in ("cameras", "image_size", "image_channels", "image_features"):
        saved.pop(key)
    (tmp_path / "old" / "config.json").write_text(json.dumps(saved))
    assert Policy.from_pretrained(tmp_path / "old").config == state.config
    with pytest.raises(ValueError, match="image_size"):
        FlowPolicyConfig(cameras="corner", image_size=8)


def test_instruction_variants_are_looked_up_per_episode():
    processor = ObservationProcessor(state_dim=2, lang_dim=384)
    tasks = [["push the puck to the goal", "nudge the disc onto the marker"], ["pull the drawer open"]]
    processor.bind_instructions(tasks)
    raw = {"state": torch.zeros(3, 2), "task": torch.tensor([0, 0, 1])}
    canonical = processor(raw)["lang"]
    varied = processor(raw | {"instruction": torch.tensor([0, 1, 0])})["lang"]
    torch.testing.assert_close(varied[[0, 2]], canonical[[0, 2]])
    assert not torch.allclose(varied[1], canonical[1])  # the paraphrase has its own embedding
    torch.testing.assert_close(varied[1], processor.instruction_table[1])
    with pytest.raises(ValueError, match="out of range"):
        processor(raw | {"instruction": torch.tensor([0, 0, 1])})  # task 1 has one variant
    with processor.bound(["turn the dial", "press the button"]):
        assert processor.instructions == ["turn the dial", "press the button"]
        assert not torch.allclose(processor(raw)["lang"], canonical)
    assert processor.instruction_variants == tasks  # restored after the block
    torch.testing.assert_close(processor(raw)["lang"], canonical)
