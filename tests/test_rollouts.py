"""Noisy expert rollouts for a world model: reproducible noise, stored beside the
demonstrations, never trained on by policies, trained on by a world model that asks for them."""

from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from collectors.collect import CollectConfig, collect
from collectors.experts import ActionNoise
from collectors.storage import DatasetError, DemoDataset

SMALL = {"image_size": 48, "num_points": 128}


def test_action_noise_depends_on_the_episode_seed_and_step_only():
    def noisy(seed: int, step: int) -> torch.Tensor:
        td = TensorDict({"action": torch.zeros(4), "episode_seed": torch.tensor([seed]),
                         "step_count": torch.tensor([step])}, [])
        return ActionNoise(0.3)(td)["action"]

    assert torch.equal(noisy(5, 2), noisy(5, 2)) and not torch.equal(noisy(5, 2), noisy(5, 3))
    assert not torch.equal(noisy(5, 2), noisy(6, 2))
    expected = np.random.default_rng([5, 2]).normal(0.0, 0.3, size=4)
    np.testing.assert_allclose(noisy(5, 2).numpy(), np.clip(expected, -1, 1), atol=1e-6)
    assert ActionNoise(50.0)(TensorDict({"action": torch.zeros(4), "episode_seed": torch.tensor([0]),
                                         "step_count": torch.tensor([0])}, []))["action"].abs().max() == 1.0


@pytest.fixture
def with_rollouts(reach_data, tmp_path) -> str:
    data = tmp_path / "reach"
    shutil.copytree(reach_data, data)
    collect(CollectConfig(tasks=("reach",), out=str(data), episodes=2, seed=1000, append=True, env_kwargs=SMALL,
                          action_noise=0.5, keep_failures=True, progress=False))
    return str(data)


def test_rollouts_are_stored_after_the_demonstrations_and_kept_from_policies(with_rollouts):
    dataset = DemoDataset.open(with_rollouts)
    assert dataset.rollout_episodes() == [2, 3] and [e.length for e in dataset.metadata.episodes[2:]] == [200, 200]
    demonstrations = dataset.demonstrations()
    assert [e.index for e in demonstrations.metadata.episodes] == [0, 1]
    assert demonstrations.num_frames == sum(e.length for e in dataset.metadata.episodes[:2])
    with pytest.raises(DatasetError, match="action noise 0.5"):  # the same seed resumes only the same collection
        collect(CollectConfig(tasks=("reach",), out=with_rollouts, episodes=3, seed=1000, append=True,
                              env_kwargs=SMALL, progress=False))


def test_a_policy_never_trains_on_rollouts_and_a_world_model_does_when_asked(with_rollouts, reach_data, tmp_path,
                                                                          monkeypatch):
    import d2a_agents.world_model.train as wm_train
    from d2a_agents.policy.agent import PolicyConfig
    from d2a_agents.policy.networks import EncoderConfig, VelocityNetConfig
    from d2a_agents.policy.train import TrainPolicyConfig, train_policy
    from d2a_agents.world_model.triplane import WorldModelConfig

    policy = PolicyConfig(algo="mp1", num_points=32, encoder=EncoderConfig(point_widths=(8,)),
                          network=VelocityNetConfig(hidden=16, layers=1))
    trained, _ = train_policy(TrainPolicyConfig(data=with_rollouts, out=str(tmp_path / "run"), policy=policy, steps=1,
                                                batch_size=4, eval_episodes=0, trim_after_success=-1, progress=False))
    dataset = DemoDataset.open(with_rollouts)
    demos = torch.cat([dataset.episode(i)["action"] for i in (0, 1)])
    assert torch.allclose(trained.normalizers["action"].low.float(), demos.min(0).values)

    tables = []
    real = wm_train.WorldModelTransitions
    monkeypatch.setattr(wm_train, "WorldModelTransitions",
                        lambda *args, **kwargs: tables.append(list(args[4])) or real(*args, **kwargs))
    wm = wm_train.TrainWorldModelConfig(
        data=with_rollouts, out=str(tmp_path / "wm.pt"), model=WorldModelConfig(resolution=(16, 16, 8)), steps=1,
        batch_size=2, queries=64, validate_every=1, validation_stride=50, progress=False)
    wm_train.train_world_model(wm)
    wm_train.train_world_model(dataclasses.replace(wm, out=str(tmp_path / "wm_rollouts.pt"), with_rollouts=True))
    # (training, held-out) episodes of each run: the demonstrations split alike, the rollouts added to training.
    assert tables == [[0], [1], [0, 2, 3], [1]]
    with pytest.raises(ValueError, match="holds no rollouts"):
        wm_train.train_world_model(dataclasses.replace(wm, data=reach_data, out=str(tmp_path / "x.pt"),
                                                       with_rollouts=True))


def test_dart_noise_perturbs_what_runs_and_stores_the_experts_label(tmp_path):
    """Each stored action is the scripted expert's own action in the stored state (recomputed
    here), while the executed, noisy actions move the hand off the clean demonstration."""
    from metaworld.policies import ENV_POLICY_MAP

    clean = DemoDataset.open(collect(CollectConfig(tasks=("reach",), out=str(tmp_path / "clean"), episodes=1,
                                                   env_kwargs=SMALL, progress=False)).directory)
    dart = DemoDataset.open(collect(CollectConfig(tasks=("reach",), out=str(tmp_path / "dart"), episodes=1,
                                                  env_kwargs=SMALL, dart_noise=0.5, progress=False)).directory)
    assert dart.metadata.collections[0].dart_noise == 0.5 and dart.rollout_episodes() == []  # demonstrations
    episode = dart.episode(0)
    expert = ENV_POLICY_MAP["reach-v3"]()
    labels = np.stack([np.clip(expert.get_action(state), -1, 1) for state in episode["state"].double().numpy()])
    np.testing.assert_allclose(episode["action"].numpy(), labels, atol=1e-5)
    steps = min(len(episode["state"]), clean.metadata.episodes[0].length)
    assert not torch.allclose(episode["state"][:steps, :3], clean.episode(0)["state"][:steps, :3], atol=1e-3)
    with pytest.raises(DatasetError, match="DART noise 0.5"):  # resumed only with the same noise
        collect(CollectConfig(tasks=("reach",), out=str(tmp_path / "dart"), episodes=2, append=True,
                              env_kwargs=SMALL, progress=False))
    with pytest.raises(ValueError, match="choose one of action noise"):
        collect(CollectConfig(tasks=("reach",), out=str(tmp_path / "both"), episodes=1, env_kwargs=SMALL,
                              action_noise=0.1, dart_noise=0.1, progress=False))
