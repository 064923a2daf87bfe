"""How well does a policy predict the expert on demonstrations it never saw? (``d2a bench policy-fit``)

Success over 100 episodes is a noisy reading of a policy, and at 1-5 demonstrations the spread
between training seeds can hide what an input adds. The one-step error on the demonstrations
after the ones a policy trained on is a quieter one: for each policy, the normalized action
error of its acting (EMA) weights on windows of the episodes it trained on and of the unseen
ones after them (frames past each first success trimmed as in training), each with its
reliance ratios (that error with the clouds, or its second cloud alone, shuffled across the
windows: :func:`~d2a_agents.policy.perception.reliance`).
Each policy reads its second cloud as it trained: ``d2a`` its world model's imagination of
every step, ``d2a-oracle`` the demonstration's own cloud H steps ahead, ``d2a-present`` the
present again.

Example::

    run(PolicyFitConfig(policies=("outputs/table4/runs/push_d2a-oracle_s0_e5_fresh_d2_num_points128",
                                  "outputs/table4/runs/push_d2a-present_s0_e5_fresh_d2_num_points128")))
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict

from collectors.dataset import DemoWindows, WindowConfig
from collectors.storage import DemoDataset
from d2a_agents.policy.agent import Policy
from d2a_agents.policy.checkpoints import load_policy
from d2a_agents.policy.perception import Reliance, reliance
from d2a_agents.policy.train import frames_up_to_success, training_frames
from d2a_agents.world_model.imagine import Imaginer


@dataclass(frozen=True)
class PolicyFitConfig:
    """What ``d2a bench policy-fit`` measures."""

    policies: tuple[str, ...]  # checkpoints or run directories
    data: str | None = None  # default: the data set each policy trained on
    demos: int | None = None  # default: each policy's own count (its first episodes of each task)
    windows: int = 512  # at most this many windows per split (a seeded draw)
    seed: int = 0  # the draw of windows and of the samplers' noise
    # "zeros": a d2a policy's world model imagines from no past actions (as at an episode's
    # start), so the check tells how much of its fit comes through the actions the model reads
    past_actions: str = "recorded"

    def __post_init__(self) -> None:
        if not self.policies:
            raise ValueError("name at least one policy")
        if self.past_actions not in ("recorded", "zeros"):
            raise ValueError(f"past_actions must be 'recorded' or 'zeros', not {self.past_actions!r}")
        if self.windows < 2 or (self.demos is not None and self.demos < 1):
            raise ValueError(f"windows must be at least 2 and demos at least 1, got {self.windows} and {self.demos}")


def _frames(dataset: DemoDataset, policy: Policy, payload: dict[str, Any], past_actions: str) -> TensorDict:
    """The frames the policy reads, as in its training: its second cloud made the same way
    (unless ``past_actions`` is "zeros"), the frames past each episode's first success trimmed
    the same way."""
    config = policy.config
    imaginer = (Imaginer.from_checkpoint(payload["world_model"], num_points=config.imagined_point_count,
                                         output=config.variant.imagined) if payload.get("world_model") else None)
    if imaginer is not None and past_actions == "zeros":  # the model then reads zeros for them
        imaginer.model.config = dataclasses.replace(imaginer.config, reads_actions=False)
    frames = training_frames(dataset, config, imaginer, progress=False)
    keep_after = payload["train_config"].get("trim_after_success", -1)
    return frames[frames_up_to_success(frames, keep_after)] if keep_after >= 0 else frames


def _split_reliance(policy: Policy, frames: TensorDict, episodes: list[int], config: PolicyFitConfig) -> Reliance:
    keys = policy.config.observation_keys
    windows = DemoWindows(frames, WindowConfig(policy.config.horizon, policy.config.n_obs_steps,
                                               policy.config.n_action_steps, keys), episodes=episodes)
    chosen = torch.randperm(len(windows), generator=torch.Generator().manual_seed(config.seed))[: config.windows]
    batch = windows.get(chosen)
    return reliance(policy, {key: batch["obs", key] for key in keys}, batch["action"], seed=config.seed)


def run(config: PolicyFitConfig) -> dict[str, dict[str, Reliance]]:
    """Per policy (its run's name), per split ("trained on", "unseen"): its :class:`Reliance`."""
    print("\n| policy | episodes | count | windows | one-step error | clouds shuffled | second cloud shuffled |")
    print("| --- | --- | --- | --- | --- | --- | --- |", flush=True)
    results: dict[str, dict[str, Reliance]] = {}
    made: dict[str, TensorDict] = {}  # frames by what makes them: the seeds of one method share theirs
    for path in config.policies:
        policy, payload = load_policy(path)
        demos = config.demos or payload["train_config"].get("demos")
        data = config.data or payload["data"]
        dataset = DemoDataset.open_for_training(data).demonstrations()  # never a world model's rollouts
        if demos is None:
            raise ValueError(f"{path} trained on every episode of {data}: pass the count it trained on")
        trained = [episode.index for episode in dataset.first_episodes(demos).metadata.episodes]
        unseen = [episode.index for episode in dataset.metadata.episodes if episode.index not in trained]
        if not unseen:
            raise ValueError(f"{data} holds no demonstration after the first {demos} of each task")
        recipe = json.dumps([data, payload["policy_config"], payload.get("world_model"),
                             payload["train_config"].get("trim_after_success", -1)], sort_keys=True, default=str)
        if recipe not in made:
            made[recipe] = _frames(dataset, policy, payload, config.past_actions)
        frames = made[recipe]
        name = Path(path).name
        results[name] = {}
        for split, episodes in (("trained on", trained), ("unseen", unseen)):
            check = results[name][split] = _split_reliance(policy, frames, episodes, config)
            second = "-" if check.imagined_ratio is None else f"x{check.imagined_ratio:.2f}"
            clouds = "-" if check.cloud_ratio is None else f"x{check.cloud_ratio:.2f}"
            print(f"| {name} | {split} | {len(episodes)} | {check.windows} | {check.intact:.4f} | {clouds} | "
                  f"{second} |", flush=True)
    return results
