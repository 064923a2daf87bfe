"""What an imagination costs and how close it comes: latency per control step and Chamfer
distance to the true future cloud, on stored demonstrations."""

from __future__ import annotations

import statistics
import time
from pathlib import Path

import numpy as np
import torch

from collectors.storage import DemoDataset
from d2a_agents.reward import chamfer_distance
from d2a_agents.world_model.data import WorldModelTransitions
from d2a_agents.world_model.imagine import Imaginer, occupancy_to_points
from d2a_envs.sampling import sample_to_size


def imagination_latency(
    checkpoint: Path, dataset: DemoDataset, steps: int, num_points: int | None = None, grow: bool = True
) -> float:
    """Median seconds of one imagination (voxelize, encode, decode near the present, FPS to
    ``num_points``; default: the checkpoint's) over ``steps`` stored transitions spread over the
    data set, each with its recorded action history (the decoding follows what the model moves,
    so the cost depends on the scene and the actions; ``grow=False`` decodes the whole band)."""
    imaginer = Imaginer.from_checkpoint(checkpoint, num_points=num_points, grow=grow)
    frames = dataset.frames()
    config = imaginer.config
    transitions = WorldModelTransitions(frames, imaginer.grid, config.horizon, config.action_history)
    positions = torch.linspace(0, len(transitions) - 1, min(steps, len(transitions))).long()
    clouds = frames["point_cloud"][transitions.rows[positions]]
    actions = transitions.past_actions(positions)
    timings = []
    for cloud, history in zip(clouds, actions, strict=True):
        start = time.perf_counter()
        imaginer(cloud, history)
        timings.append(time.perf_counter() - start)
    return statistics.median(timings)


def imagination_chamfer(
    checkpoint: Path, dataset: DemoDataset, episodes: list[int], stride: int
) -> dict[str, float]:
    """Mean Chamfer distance (m) to the cloud H steps ahead over every ``stride``-th held-out step.

    Keys: ``imagined`` (the env's decoding, observed points kept), ``centres`` (voxel centres
    only), ``persistence`` (the current cloud itself) and ``oracle`` (the true future occupancy
    decoded like ``imagined``: what a perfect occupancy model on this grid would give).
    """
    frames = dataset.frames()
    sums = dict(imagined=0.0, centres=0.0, persistence=0.0, oracle=0.0)
    decoders = {"imagined": Imaginer.from_checkpoint(checkpoint, keep_observed_points=True),
                "centres": Imaginer.from_checkpoint(checkpoint, keep_observed_points=False)}
    imaginer = decoders["imagined"]
    grid, config = imaginer.grid, imaginer.config
    transitions = WorldModelTransitions(frames, grid, config.horizon, config.action_history, episodes)
    rng = np.random.default_rng(0)
    positions = range(0, len(transitions), stride)
    for position in positions:
        cloud = torch.as_tensor(frames["point_cloud"][transitions.rows[position]])[:, :3]
        future = torch.as_tensor(frames["point_cloud"][transitions.targets[position]])[:, :3]
        actions = transitions.past_actions(torch.tensor([position]))[0]
        for name, decoder in decoders.items():
            sums[name] += chamfer_distance(decoder(cloud, actions), future)
        sums["persistence"] += chamfer_distance(cloud, future)
        oracle = occupancy_to_points(grid, grid.voxelize(future).nonzero(), cloud, grid.voxelize(cloud), True)
        sums["oracle"] += chamfer_distance(sample_to_size(oracle.numpy(), imaginer.num_points, rng), future)
    return {name: total / len(positions) for name, total in sums.items()}
