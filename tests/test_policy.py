"""Policy configuration, its inputs, and acting: the observation history and the action queue."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from collectors.dataset import Normalizer
from d2a_agents.policy.agent import Policy, PolicyConfig
from d2a_agents.policy.diffusion import Diffusion
from d2a_agents.policy.meanflow import MeanFlow, MeanFlowConfig
from d2a_agents.policy.networks import EncoderConfig, VelocityNetConfig

TINY = dict(num_points=16, encoder=EncoderConfig(point_widths=(8,)), network=VelocityNetConfig(hidden=16, layers=1))


def unit_normalizers(state_dim: int = 4) -> dict[str, Normalizer]:
    return {"action": Normalizer(-torch.ones(4), torch.ones(4)),
            "agent_pos": Normalizer(-torch.ones(4), torch.ones(4)),
            "state": Normalizer(-torch.ones(state_dim), torch.ones(state_dim)),
            "point_cloud": Normalizer(-torch.ones(3), torch.ones(3))}


def tiny_policy(algo: str, **changes) -> Policy:
    return Policy(PolicyConfig(algo=algo, **{**TINY, **changes}), 4, 4, unit_normalizers())


@pytest.mark.parametrize("algo, expert, cfg, imagination, keys, time_scale", [
    ("d2a", MeanFlow, True, True, ("point_cloud", "agent_pos", "imagined_point_cloud"), 1.0),
    ("d2a-no-cfg", MeanFlow, False, True, ("point_cloud", "agent_pos", "imagined_point_cloud"), 1.0),
    ("d2a-no-imagination", MeanFlow, True, False, ("point_cloud", "agent_pos"), 1.0),
    ("d2a-present", MeanFlow, True, True, ("point_cloud", "agent_pos"), 1.0),  # 2nd encoder: the cloud again
    ("d2a-oracle", MeanFlow, True, True, ("point_cloud", "agent_pos", "imagined_point_cloud"), 1.0),
    ("mp1", MeanFlow, False, False, ("point_cloud", "agent_pos"), 1.0),
    ("dp3", Diffusion, None, False, ("point_cloud", "agent_pos"), 1000.0),
    ("mp1-state", MeanFlow, False, False, ("state",), 1.0),
    ("dp3-state", Diffusion, None, False, ("state",), 1000.0),
])
def test_algo_flag_selects_expert_cfg_imagination_and_inputs(algo, expert, cfg, imagination, keys, time_scale):
    policy = tiny_policy(algo, cfg_thresholds=(-0.5, 0.25), cfg_similarity="velocity", adaptive_power=0.5,
                         cfg_guidance="amplify", cfg_scale=3.0)
    assert isinstance(policy.expert, expert)
    assert policy.config.encoder.use_imagination is imagination
    assert policy.config.observation_keys == keys
    assert (policy.encoder.cloud is None) == ("point_cloud" not in keys)
    assert policy.config.network.time_scale == time_scale
    if expert is MeanFlow:
        assert policy.expert.config.adaptive_power == 0.5
    else:
        assert policy.expert.config.prediction_type == "sample"  # as DP3 configures it
    if cfg is not None:
        assert policy.expert.config.cfg_enabled is cfg
        assert (policy.expert.config.tau_l, policy.expert.config.tau_h) == (-0.5, 0.25)
        assert policy.expert.config.cfg_similarity == "velocity"  # not the default
        assert (policy.expert.config.cfg_guidance, policy.expert.config.cfg_scale) == ("amplify", 3.0)


def test_config_round_trip_and_bad_algo():
    config = PolicyConfig(algo="mp1", horizon=16, n_obs_steps=2, n_action_steps=8, cfg_thresholds=(-1.0, 0.0),
                          cfg_similarity="velocity", **TINY)
    assert PolicyConfig.from_dict(config.to_dict()) == config
    assert config.executed_actions == 8
    assert PolicyConfig(algo="mp1").executed_actions == 3  # horizon 4 starting at the older of 2 observations
    with pytest.raises(ValueError, match="unknown algo"):
        PolicyConfig(algo="ppo")


def recorded_plans(policy: Policy, monkeypatch) -> list[dict[str, torch.Tensor]]:
    """The observation windows the policy plans from, appended as it plans."""
    windows = []
    original = policy.predict_action_chunk

    def recording(window, generator=None):
        windows.append({key: value.clone() for key, value in window.items()})
        return original(window, generator)

    monkeypatch.setattr(policy, "predict_action_chunk", recording)
    return windows


def test_policy_plans_once_per_chunk_and_forgets_on_reset(monkeypatch):
    policy = tiny_policy("mp1")
    windows = recorded_plans(policy, monkeypatch)
    rng = np.random.default_rng(0)

    def observation(value: float) -> dict[str, np.ndarray]:
        return {"point_cloud": rng.random((32, 3)).astype(np.float32), "agent_pos": np.full(4, value, np.float32)}

    policy.reset(seed=0)
    actions = [policy.select_action(observation(float(step))) for step in range(7)]
    assert len(windows) == 3  # steps 0, 3 and 6 plan; 3 actions executed per chunk
    assert all(action.shape == (4,) and np.isfinite(action).all() for action in actions)
    assert windows[0]["agent_pos"][0, :, 0].tolist() == [0.0, 0.0]  # first frame repeated
    assert windows[1]["agent_pos"][0, :, 0].tolist() == [2.0, 3.0]  # the two latest observations
    assert windows[0]["point_cloud"].shape == (1, 2, 16, 3)  # FPS to num_points
    policy.reset(seed=0)
    policy.select_action(observation(9.0))
    assert len(windows) == 4 and windows[3]["agent_pos"][0, :, 0].tolist() == [9.0, 9.0]


@pytest.mark.parametrize("n_action_steps, planned_at", [(1, list(range(7))), (2, [0, 2, 4, 6]), (9, [0, 3, 6])])
def test_n_action_steps_sets_how_often_the_policy_plans(n_action_steps, planned_at, monkeypatch):
    """Executed actions per chunk: n_action_steps, at most the chunk's actions from the current step on."""
    policy = tiny_policy("mp1", n_action_steps=n_action_steps)
    windows = recorded_plans(policy, monkeypatch)
    cloud = np.random.default_rng(0).random((32, 3)).astype(np.float32)
    policy.reset(seed=0)
    for step in range(7):
        policy.select_action({"point_cloud": cloud, "agent_pos": np.full(4, step, np.float32)})
    assert [int(window["agent_pos"][0, -1, 0]) for window in windows] == planned_at  # the latest observation's step
    with pytest.raises(ValueError, match="n_action_steps must be at least 1"):
        PolicyConfig(algo="mp1", n_action_steps=0)


def test_an_episode_s_actions_depend_on_its_seed_only():
    policy = tiny_policy("mp1")
    observation = {"point_cloud": np.random.default_rng(1).random((32, 3)).astype(np.float32),
                   "agent_pos": np.zeros(4, np.float32)}
    policy.reset(seed=5)
    first = policy.select_action(observation)
    policy.reset(seed=6)
    other = policy.select_action(observation)
    policy.reset(seed=5)
    np.testing.assert_array_equal(policy.select_action(observation), first)
    assert not np.array_equal(first, other)


def test_clouds_are_normalized_per_axis_inside_the_policy():
    """Both clouds map through the current cloud's min/max per axis, computed here by hand."""
    low, high = torch.tensor([0.0, -1.0, 2.0]), torch.tensor([2.0, 3.0, 2.5])
    normalizers = {**unit_normalizers(), "point_cloud": Normalizer(low, high)}
    policy = Policy(PolicyConfig(algo="d2a", **TINY), 4, 4, normalizers)
    cloud = torch.tensor([[[[1.0, 1.0, 2.25], [2.0, 3.0, 2.0]]]])  # (B=1, n_obs=1, N=2, 3)
    expected = torch.tensor([[[[0.0, 0.0, 0.0], [1.0, 1.0, -1.0]]]])
    window = {"point_cloud": cloud, "imagined_point_cloud": cloud + 1.0, "agent_pos": torch.zeros(1, 1, 4)}
    normalized = policy.normalize_observation(window)
    torch.testing.assert_close(normalized["point_cloud"], expected)
    torch.testing.assert_close(normalized["imagined_point_cloud"], expected + torch.tensor([1.0, 0.5, 4.0]))


def test_the_present_control_feeds_the_current_cloud_to_its_second_encoder():
    """d2a-present reads no imagined cloud from the env: its second encoder gets the current one."""
    policy = tiny_policy("d2a-present")
    cloud = torch.rand(1, 2, 16, 3)
    window = {"point_cloud": cloud, "agent_pos": torch.zeros(1, 2, 4)}
    normalized = policy.normalize_observation(window)
    torch.testing.assert_close(normalized["imagined_point_cloud"], normalized["point_cloud"])
    shown = policy.normalize_observation({**window, "imagined_point_cloud": cloud.flip(2) + 0.5})
    assert not torch.allclose(shown["imagined_point_cloud"], shown["point_cloud"])  # an explicit copy wins


@pytest.mark.parametrize("imagined_steps", [1, 2])
def test_the_imagined_encoder_reads_the_latest_imagined_clouds(imagined_steps):
    """With imagined_steps = 1 (the paper's one P_{t+H}) only the latest imagined cloud enters
    the condition; with 2 the older one does too."""
    from d2a_agents.policy.networks import ObservationEncoder

    config = EncoderConfig(point_widths=(8,), imagined_steps=imagined_steps)
    torch.manual_seed(0)
    encoder = ObservationEncoder(config, state_dim=4)
    observation = {"point_cloud": torch.rand(3, 2, 16, 3), "agent_pos": torch.rand(3, 2, 4),
                   "imagined_point_cloud": torch.rand(3, 2, 16, 3)}
    features = encoder(observation)
    assert features.shape == (3, (2 * 2 + imagined_steps) * config.embed_dim) == (3, encoder.out_dim)
    older, latest = (observation["imagined_point_cloud"].clone() for _ in range(2))
    older[:, 0] += 1.0
    latest[:, 1] += 1.0
    assert not torch.allclose(encoder({**observation, "imagined_point_cloud": latest}), features)
    moved_older = encoder({**observation, "imagined_point_cloud": older})
    assert torch.allclose(moved_older, features) == (imagined_steps == 1)
    with pytest.raises(ValueError, match="imagined_steps"):
        EncoderConfig(imagined_steps=3)


def test_stacked_oracle_horizons_are_encoded_apart_nearest_first():
    """d2a-oracle with stacked horizons reads K clouds per observation, each through the
    imagined-cloud encoder on its own: the condition ends with their K encodings in horizon order."""
    policy = tiny_policy("d2a-oracle", oracle_horizon=4, stacked_horizons=(2, 1))
    assert policy.config.oracle_horizons == (1, 2, 4) and policy.config.encoder.imagined_clouds == 3
    encoder, embed = policy.encoder, policy.config.encoder.embed_dim
    torch.manual_seed(0)
    futures = torch.rand(3, 2, 3, 16, 3)
    observation = {"point_cloud": torch.rand(3, 2, 16, 3), "agent_pos": torch.rand(3, 2, 4),
                   "imagined_point_cloud": futures}
    features = encoder(observation)
    assert features.shape == (3, (2 * 2 + 3) * embed) == (3, encoder.out_dim)
    for k in range(3):  # the latest observation's k-th cloud, encoded alone
        alone = encoder.imagined(futures[:, -1, k])
        torch.testing.assert_close(features[:, (4 + k) * embed:(5 + k) * embed], alone)
    assert tiny_policy("d2a", stacked_horizons=(1,)).config.encoder.imagined_clouds == 1  # the oracle's alone
    with pytest.raises(ValueError, match="repeat"):
        PolicyConfig(algo="d2a-oracle", oracle_horizon=4, stacked_horizons=(4,))
    with pytest.raises(ValueError, match="at least 1"):
        PolicyConfig(algo="d2a-oracle", stacked_horizons=(0,))
    raw = PolicyConfig(algo="d2a-oracle", stacked_horizons=(1, 2)).to_dict()
    raw["stacked_horizons"] = list(raw["stacked_horizons"])  # as a checkpoint's JSON holds it
    assert PolicyConfig.from_dict(raw) == PolicyConfig(algo="d2a-oracle", stacked_horizons=(1, 2))


def test_a_policy_without_its_normalizers_is_refused():
    normalizers = unit_normalizers()
    del normalizers["point_cloud"]
    with pytest.raises(ValueError, match="point_cloud"):
        Policy(PolicyConfig(algo="mp1", **TINY), 4, 4, normalizers)
    Policy(PolicyConfig(algo="mp1-state", **TINY), 4, 4, normalizers)  # reads no cloud


def test_raw_clouds_get_the_identity_normalizer():
    from tensordict import TensorDict

    from d2a_agents.policy.train import fit_policy_normalizers

    frames = TensorDict({"point_cloud": torch.rand(5, 8, 3) * 3 + 2, "agent_pos": torch.rand(5, 4),
                         "action": torch.rand(5, 4)}, batch_size=[5])
    cloud = frames["point_cloud"][:1]
    fitted = fit_policy_normalizers(frames, PolicyConfig(algo="mp1", **TINY))["point_cloud"]
    raw = fit_policy_normalizers(frames, PolicyConfig(algo="mp1", normalize_clouds=False, **TINY))["point_cloud"]
    torch.testing.assert_close(raw.normalize(cloud), cloud)
    low, high = frames["point_cloud"].reshape(-1, 3).amin(0), frames["point_cloud"].reshape(-1, 3).amax(0)
    torch.testing.assert_close(fitted.normalize(cloud), (cloud - (low + high) / 2) / ((high - low) / 2))


def test_bfloat16_point_mlp_matches_float32_and_keeps_float32_weights():
    """Same weights, two precisions: the bf16 encoder's features agree with the float32 ones to
    bf16's resolution, gradients reach the float32 weights, and a bad dtype is refused."""
    from d2a_agents.policy.networks import PointCloudEncoder

    torch.manual_seed(0)
    exact = PointCloudEncoder((32, 64), 16, point_dtype="float32")
    fast = PointCloudEncoder((32, 64), 16, point_dtype="bfloat16")
    fast.load_state_dict(exact.state_dict())
    points = torch.rand(8, 2, 64, 3) * 2 - 1
    reference, features = exact(points), fast(points)
    assert features.dtype == torch.float32
    assert not torch.equal(features, reference)  # the MLP really ran in bf16
    assert (features - reference).abs().max() < 0.05 * reference.abs().max()
    features.square().mean().backward()
    first = fast.point_mlp[0].weight
    assert first.dtype == torch.float32 and first.grad is not None and first.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="point_dtype"):
        EncoderConfig(point_dtype="float16")


def test_the_expert_and_the_policy_default_to_the_same_cfg_thresholds():
    expert = MeanFlowConfig()
    assert (expert.tau_l, expert.tau_h) == PolicyConfig().cfg_thresholds


def test_acting_on_the_mean_of_k_draws_divides_the_sampler_spread_by_k():
    """One window repeated 2000 times, each row its own noise: the chunks' variance across rows
    is the sampler's spread; the mean of 4 independent draws has a quarter of it, the same mean."""
    policy = tiny_policy("mp1").eval()
    rows = 2000
    window = {"point_cloud": torch.rand(1, 2, 16, 3).expand(rows, -1, -1, -1),
              "agent_pos": torch.rand(1, 2, 4).expand(rows, -1, -1)}
    with torch.no_grad():
        one = policy.sample_normalized(window, torch.Generator().manual_seed(0))
        policy.action_draws = 4
        four = policy.sample_normalized(window, torch.Generator().manual_seed(1))
    assert four.shape == one.shape == (rows, 4, 4)
    ratio = four.var(0) / one.var(0)  # per action entry; relative error of each about 3 %
    assert 0.2 < ratio.mean() < 0.3 and ratio.min() > 0.15 and ratio.max() < 0.35
    assert torch.allclose(four.mean(0), one.mean(0), atol=5 * float(one.std(0).max()) / rows ** 0.5)
