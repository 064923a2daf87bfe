"""The 2D Diffusion Policy: its image encoder against hand computations, its config, and learning."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from collectors.dataset import Normalizer
from d2a_agents.policy.agent import Policy, PolicyConfig
from d2a_agents.policy.diffusion import Diffusion
from d2a_agents.policy.image_encoder import (
    ImageEncoder,
    ImageEncoderConfig,
    SpatialSoftmax,
    crop_images,
    group_norm,
    resnet18_trunk,
)
from d2a_agents.policy.networks import EncoderConfig, VelocityNetConfig
from d2a_agents.policy.perception import reliance

TINY_IMAGE_POLICY = dict(encoder=EncoderConfig(image_widths=(4, 4, 8, 8), embed_dim=16),
                         network=VelocityNetConfig(hidden=64, layers=2))


def test_spatial_softmax_is_the_softmax_weighted_mean_pixel_position():
    head = SpatialSoftmax(channels=1, keypoints=1)
    with torch.no_grad():
        head.keypoint_maps.weight.fill_(1.0)
        head.keypoint_maps.bias.zero_()
    logits = [[0.0, 1.0, 2.0], [3.0, -1.0, 0.5]]  # 2 rows, 3 columns
    weights = [[math.exp(v) for v in row] for row in logits]
    total = sum(map(sum, weights))
    xs, ys = [-1.0, 0.0, 1.0], [-1.0, 1.0]  # pixel centres from left to right, top to bottom
    expected_x = sum(weights[r][c] * xs[c] for r in range(2) for c in range(3)) / total
    expected_y = sum(weights[r][c] * ys[r] for r in range(2) for c in range(3)) / total
    out = head(torch.tensor(logits)[None, None])
    assert out.shape == (1, 2)
    assert out[0].tolist() == pytest.approx([expected_x, expected_y], abs=1e-6)


def test_a_peaked_keypoint_map_points_at_its_pixel():
    head = SpatialSoftmax(channels=1, keypoints=1)
    with torch.no_grad():
        head.keypoint_maps.weight.fill_(1.0)
        head.keypoint_maps.bias.zero_()
    features = torch.full((1, 1, 5, 9), -50.0)
    features[0, 0, 4, 2] = 50.0  # bottom row, third column
    assert head(features)[0].tolist() == pytest.approx([2 / 8 * 2 - 1, 1.0], abs=1e-5)


def test_crops_are_windows_of_their_own_image():
    images = torch.arange(3 * 10 * 12 * 2, dtype=torch.int64).reshape(3, 10, 12, 2)
    centre = crop_images(images, 6, random=False)
    assert torch.equal(centre, images[:, 2:8, 3:9])
    generator = torch.Generator().manual_seed(0)
    crops = crop_images(images, 6, generator=generator)
    offsets = set()
    for image, crop in zip(images, crops, strict=True):
        found = [(top, left) for top in range(5) for left in range(7)
                 if torch.equal(image[top:top + 6, left:left + 6], crop)]
        assert len(found) == 1
        offsets.add(found[0])
    assert len(offsets) > 1  # each image its own window


def test_resnet18_trunk_shapes_and_group_norm():
    trunk = resnet18_trunk((64, 128, 256, 512))
    # 84 -> stem /2 -> 42 -> max-pool /2 -> 21 -> stages /1 /2 /2 /2 -> 21, 11, 6, 3
    assert trunk(torch.zeros(1, 3, 84, 84)).shape == (1, 512, 3, 3)
    convolutions = [m for m in trunk.modules() if isinstance(m, torch.nn.Conv2d)]
    assert len(convolutions) == 1 + 16 + 3  # the stem, two convolutions per block, three projections
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in trunk.modules())
    assert group_norm(64).num_groups == 4 and group_norm(8).num_groups == 1


def test_the_encoder_crops_randomly_in_training_and_in_the_centre_otherwise():
    encoder = ImageEncoder(ImageEncoderConfig(widths=(4, 4, 8, 8)), out_dim=8)
    images = torch.randint(0, 256, (2, 3, 72, 72, 3), dtype=torch.uint8)
    assert encoder(images).shape == (2, 3, 8)
    encoder.eval()
    assert torch.equal(encoder(images), encoder(images))
    encoder.train()
    torch.manual_seed(0)
    assert not torch.equal(encoder(images), encoder(images))
    with pytest.raises(ValueError, match="four stages"):
        ImageEncoderConfig(widths=(4, 8))
    with pytest.raises(ValueError, match="1x1 map"):  # 32 pixels: one feature-map cell, no position to find
        encoder(torch.zeros(1, 35, 35, 3))


def image_policy(**changes) -> Policy:
    normalizers = {"action": Normalizer(-torch.ones(4), torch.ones(4)),
                   "agent_pos": Normalizer(-torch.ones(4), torch.ones(4))}
    return Policy(PolicyConfig(algo="dp", **{**TINY_IMAGE_POLICY, **changes}), 4, 4, normalizers)


def test_dp_reads_the_image_and_agent_pos_with_diffusion_and_records_its_image_settings():
    policy = image_policy()
    assert isinstance(policy.expert, Diffusion) and policy.expert.config.prediction_type == "sample"
    assert policy.config.observation_keys == ("image", "agent_pos")
    assert policy.encoder.cloud is None and policy.encoder.image is not None
    assert policy.encoder.out_dim == 2 * 2 * 16  # two observations of (image, agent_pos) features
    raw = policy.config.to_dict()
    assert raw["encoder"]["image_widths"] == (4, 4, 8, 8)
    assert PolicyConfig.from_dict(raw) == policy.config
    cloud_policy = PolicyConfig(algo="mp1").to_dict()
    assert "image_widths" not in cloud_policy["encoder"] and "use_image" not in cloud_policy["encoder"]


def test_dp_acts_on_raw_env_observations():
    policy = image_policy()
    observation = {"image": np.zeros((48, 48, 3), np.uint8), "agent_pos": np.zeros(4, np.float32)}
    action = policy.select_action(observation)
    assert action.shape == (4,) and action.dtype == np.float32


def test_dp_learns_an_action_that_only_its_image_tells():
    """The action is +-0.5 on every entry: + where a bright square is in the left half of the
    image, - where it is in the right half; agent_pos carries noise only. After training, the
    policy's sampled actions have the sign of the image's side, and shuffling the images
    across windows hurts its one-step error far more than shuffling agent_pos."""
    torch.manual_seed(0)
    generator = torch.Generator().manual_seed(0)

    def windows(count: int) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        left = torch.rand(count, generator=generator) < 0.5
        images = torch.zeros(count, 2, 48, 48, 3, dtype=torch.uint8)
        for index, is_left in enumerate(left.tolist()):
            column = 6 if is_left else 30
            images[index, :, 16:28, column:column + 12] = 255
        actions = torch.where(left, 0.5, -0.5)[:, None, None].expand(count, 4, 4).clone()
        return {"image": images, "agent_pos": torch.randn(count, 2, 4, generator=generator)}, actions

    policy = image_policy()
    optimizer = torch.optim.AdamW(policy.parameters(), lr=3e-3)
    for _ in range(150):
        observation, actions = windows(32)
        loss, _ = policy.compute_loss(observation, actions, generator)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    policy.eval()
    observation, actions = windows(64)
    sampled = policy.predict_action_chunk(observation, torch.Generator().manual_seed(1))
    agreement = (sampled.mean(dim=(1, 2)).sign() == actions[:, 0, 0].sign()).float().mean()
    assert agreement > 0.9
    check = reliance(policy, observation, actions)
    assert check.perceives == "images"
    assert check.cloud_ratio > 5 * check.state_ratio
