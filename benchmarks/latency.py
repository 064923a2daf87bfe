"""Inference latency at batch 1 on the CPU (``d2a bench latency``).

D2A's MeanFlow expert (1 network evaluation per chunk) against the DP3-style diffusion
expert (10 DDIM evaluations), the FlowPolicy-style consistency flow (1), the Consistency
Policy's EDM teacher and student, with the same encoders and network, the 2D Diffusion
Policy (the same diffusion on a ResNet-18's features of a camera image), and the world model's
imagination (voxelize, encode, decode near the present, FPS) per control step. The policies'
latency does not depend on the weights, so freshly initialised ones are timed on real clouds
of a D2A env. An untrained world model does not know what moves, so it decodes the whole band
around the present (an upper bound); a trained one (``world_model`` + ``data``) decodes from
the present outwards, following what it moves, and is timed on its demonstrations with their
recorded actions, at the env's cloud size and at the policy's point count.
"""

from __future__ import annotations

import dataclasses
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import torch

import d2a_envs
from collectors.dataset import Normalizer
from collectors.storage import DemoDataset
from d2a_agents.policy.agent import CPU_POLICY_PRESET, Policy, PolicyConfig
from d2a_agents.policy.edm import EDMConfig
from d2a_agents.world_model.evaluation import imagination_latency
from d2a_agents.world_model.imagine import Imaginer
from d2a_agents.world_model.triplane import CPU_PRESET, TriplaneWorldModel, WorldModelConfig
from d2a_agents.world_model.voxels import VoxelGrid


@dataclass(frozen=True)
class LatencyBenchConfig:
    """What ``d2a bench latency`` times."""

    task: str = "hammer"
    num_points: int = 1024
    rgb_image_size: int = 84  # the 2D Diffusion Policy's images (DP3's Meta-World size)
    repeats: int = 50
    world_models: tuple[WorldModelConfig, ...] = (WorldModelConfig(resolution=(32, 32, 8)), CPU_PRESET)
    world_model: str | None = None  # a trained checkpoint, timed on ``data``
    data: str | None = None
    threads: int = 1

    def __post_init__(self) -> None:
        if (self.world_model is None) != (self.data is None):
            raise ValueError("a trained world model is timed on its demonstrations: give both world_model and data")


def median_seconds(function: Callable[[], object], repeats: int) -> float:
    function()  # warm-up
    timings = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        timings.append(time.perf_counter() - start)
    return statistics.median(timings)


def run(config: LatencyBenchConfig = LatencyBenchConfig()) -> dict[str, float]:
    torch.set_num_threads(config.threads)
    spec = d2a_envs.get_task(config.task)
    env = gym.make(spec.env_id, num_points=config.num_points)
    try:
        observation, _ = env.reset(seed=0)
        action_dim, box = env.action_space.shape[0], env.get_wrapper_attr("config").crop_box
    finally:
        env.close()
    cloud = torch.as_tensor(observation["point_cloud"])
    state_dim = observation["agent_pos"].shape[0]
    normalizers = {"action": Normalizer(-torch.ones(action_dim), torch.ones(action_dim)),
                   "agent_pos": Normalizer(-torch.ones(state_dim), torch.ones(state_dim)),
                   "point_cloud": Normalizer(cloud.amin(0), cloud.amax(0))}
    results = {}
    policies = {algo: PolicyConfig(algo=algo, num_points=config.num_points)
                for algo in ("d2a", "mp1", "dp3", "flowpolicy", "edm", "cp")}
    policies["dp"] = PolicyConfig(algo="dp")
    policies["d2a cpu preset"] = dataclasses.replace(CPU_POLICY_PRESET, algo="d2a")
    policies["dp cpu preset"] = dataclasses.replace(CPU_POLICY_PRESET, algo="dp")
    # A policy's latency does not depend on what its image shows: an empty one of the size it reads.
    image = torch.zeros(config.rgb_image_size, config.rgb_image_size, 3, dtype=torch.uint8)
    for name, policy_config in policies.items():
        policy = Policy(policy_config, action_dim, state_dim, normalizers).eval()
        steps = policy_config.n_obs_steps
        window = {"agent_pos": torch.as_tensor(observation["agent_pos"]).expand(1, steps, -1)}
        if policy_config.encoder.use_cloud:
            window["point_cloud"] = cloud[: policy_config.num_points].expand(1, steps, -1, -1)
        if policy_config.encoder.use_image:
            window["image"] = image.expand(1, steps, -1, -1, -1)
        if policy_config.encoder.use_imagination:
            window["imagined_point_cloud"] = window["point_cloud"]
        results[name] = median_seconds(lambda p=policy, w=window: p.predict_action_chunk(w), config.repeats)
    for model_config in config.world_models:
        model = TriplaneWorldModel(dataclasses.replace(model_config, action_dim=action_dim))
        imaginer = Imaginer(model, VoxelGrid(box, model_config.resolution), config.num_points, grow=False)
        actions = torch.zeros(model_config.action_history, action_dim)
        name = "imagination " + "x".join(map(str, model_config.resolution)) + ", untrained, whole band"
        results[name] = median_seconds(lambda i=imaginer, a=actions: i(cloud, a), config.repeats)
    if config.world_model is not None:
        dataset = DemoDataset.open_for_training(config.data)
        for points in (None, CPU_POLICY_PRESET.num_points):
            for grow in (False, True):
                size = "the data's cloud size" if points is None else f"{points} points"
                decoding = "grown from the present" if grow else "whole band"
                name = f"imagination, trained ({Path(config.world_model).name}), {size}, {decoding}"
                results[name] = imagination_latency(Path(config.world_model), dataset, config.repeats, points, grow)
    print(f"\nbatch 1, {config.num_points} points, {config.threads} thread(s), median of {config.repeats}\n")
    print("| what | network evaluations | median ms |")
    print("| --- | --- | --- |")
    print(f"| D2A policy (MeanFlow; current + imagined cloud encoders) | 1 | {1000 * results['d2a']:.2f} |")
    print(f"| MeanFlow policy, one cloud encoder (MP1-style) | 1 | {1000 * results['mp1']:.2f} |")
    print(f"| DP3-style policy (DDIM), the same single encoder | 10 | {1000 * results['dp3']:.2f} |")
    print(f"| FlowPolicy-style policy (consistency flow, one Euler step), the same single encoder | 1 | "
          f"{1000 * results['flowpolicy']:.2f} |")
    print(f"| EDM policy (Heun, {EDMConfig().inference_steps} steps; the Consistency Policy's teacher), the same "
          f"single encoder | {2 * EDMConfig().inference_steps - 1} | {1000 * results['edm']:.2f} |")
    print(f"| Consistency Policy student (one jump), the same single encoder | 1 | {1000 * results['cp']:.2f} |")
    print(f"| 2D Diffusion Policy (DDIM; ResNet-18 on a {config.rgb_image_size}-pixel image) | 10 | "
          f"{1000 * results['dp']:.2f} |")
    print(f"| D2A policy, cpu preset ({CPU_POLICY_PRESET.num_points} points) | 1 | "
          f"{1000 * results['d2a cpu preset']:.2f} |")
    print(f"| 2D Diffusion Policy, cpu preset (a quarter of ResNet-18's widths) | 10 | "
          f"{1000 * results['dp cpu preset']:.2f} |")
    for name, seconds in results.items():
        if name.startswith("imagination"):
            print(f"| world model {name} | 1 | {1000 * seconds:.2f} |")
    print(f"\nsame encoder, DDIM 10 steps / MeanFlow 1 step: {results['dp3'] / results['mp1']:.1f}x; "
          f"DP3-style / D2A: {results['dp3'] / results['d2a']:.1f}x")
    return results


if __name__ == "__main__":
    run()
