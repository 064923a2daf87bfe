"""``d2a viz imagine``: run an episode with a world model attached and draw what it imagines."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np

from d2a_agents.reward import chamfer_distance
from d2a_envs.tasks import get_task
from d2a_envs.viz import plot_imagination


def _expert(task: str, env: gym.Env):
    """The scripted expert of a Meta-World task, or random actions elsewhere."""
    spec = get_task(task)
    if spec.suite == "metaworld":
        from metaworld.policies import ENV_POLICY_MAP

        expert = ENV_POLICY_MAP[spec.task]()
        return lambda observation: np.clip(expert.get_action(observation["state"]), -1, 1)
    return lambda observation: env.action_space.sample()


def plot_task_imagination(
    world_model: str | Path, task: str, out: str | Path, seed: int = 0, steps: tuple[int, ...] = (10, 40, 70, 100, 130),
    **env_kwargs: object,
) -> Path:
    """Drive ``task`` with its scripted expert and plot current / imagined / true future clouds."""
    spec = get_task(task)
    env = gym.make(spec.env_id, world_model=str(world_model), **env_kwargs)
    try:  # an env left open tears its GL context down at interpreter exit, noisily
        horizon = env.get_wrapper_attr("imaginer").config.horizon
        act = _expert(task, env)
        env.action_space.seed(seed)
        observation, _ = env.reset(seed=seed)
        clouds, imagined = [observation["point_cloud"]], [observation["imagined_point_cloud"]]
        for _ in range(max(steps) + horizon):
            observation, *_ = env.step(act(observation))
            clouds.append(observation["point_cloud"])
            imagined.append(observation["imagined_point_cloud"])
        box = env.get_wrapper_attr("crop_box")
    finally:
        env.close()
    frames = [
        {
            "step": t, "current": clouds[t], "imagined": imagined[t], "future": clouds[t + horizon],
            "imagined_error": chamfer_distance(imagined[t], clouds[t + horizon]),
            "persistence_error": chamfer_distance(clouds[t], clouds[t + horizon]),
        }
        for t in steps
    ]
    return plot_imagination(frames, horizon, f"{spec.env_id}: imagination {horizon} steps ahead", out, box)
