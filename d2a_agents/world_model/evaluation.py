"""What an imagination costs and how close it comes: latency per control step, Chamfer
distance to the true future cloud, and how well the imagined change finds what moves, on
stored demonstrations."""

from __future__ import annotations

import copy
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


def _one_way(source: torch.Tensor, target: torch.Tensor) -> float:
    """Mean distance (m) from each ``source`` point to its nearest ``target`` point."""
    return float(torch.cdist(source, target, compute_mode="donot_use_mm_for_euclid_dist").min(dim=1).values.mean())


def change_distances(
    checkpoint: Path, dataset: DemoDataset, episodes: list[int], stride: int, num_points: int = 64,
) -> dict[str, dict[str, float]]:
    """How close each cloud a policy could read comes to where the scene will change.

    On every ``stride``-th held-out transition t -> t + H with t >= H, the truth is the centres of
    the voxels occupied at t + H and empty at t (steps where nothing newly fills are skipped).
    Candidates, each at ``num_points`` points: ``imagined change`` (the world model's change
    cloud), ``imagined change, likeliest`` (its ``change-top`` cloud), ``observed change`` (the
    voxels newly filled from t - H to t: motion continued, what the observation history shows),
    ``present`` (the current cloud, FPS: what ``d2a-present`` reads) and ``true change`` (the
    truth itself resampled: the floor). Per candidate, the mean
    distance (m) from it to the truth (``precision``: does it point where things go) and from
    the truth to it (``coverage``), averaged over the transitions; ``transitions`` counts them.
    """
    frames = dataset.frames()
    imaginer = Imaginer.from_checkpoint(checkpoint, num_points=num_points, output="change")
    likeliest = copy.copy(imaginer)
    likeliest.output = "change-top"
    grid, horizon = imaginer.grid, imaginer.config.horizon
    transitions = WorldModelTransitions(frames, grid, horizon, imaginer.config.action_history, episodes)
    steps = torch.as_tensor(frames["step"])
    rng = np.random.default_rng(0)
    names = ("imagined change", "imagined change, likeliest", "observed change", "present", "true change")
    sums = {name: {"precision": 0.0, "coverage": 0.0} for name in names}
    count = 0

    def resample(points: torch.Tensor) -> torch.Tensor:
        return torch.as_tensor(sample_to_size(points.numpy(), num_points, rng))

    def newly_filled(before: torch.Tensor, after: torch.Tensor) -> torch.Tensor:
        return grid.centres((grid.voxelize(after) & ~grid.voxelize(before)).nonzero())

    for position in range(0, len(transitions), stride):
        row = int(transitions.rows[position])
        if int(steps[row]) < horizon:
            continue
        cloud, future, past = (torch.as_tensor(frames["point_cloud"][index])[:, :3].float()
                               for index in (row, int(transitions.targets[position]), row - horizon))
        truth = newly_filled(cloud, future)
        if len(truth) == 0:
            continue
        observed = newly_filled(past, cloud)
        actions = transitions.past_actions(torch.tensor([position]))[0]
        candidates = {
            "imagined change": torch.as_tensor(imaginer(cloud, actions)),
            "imagined change, likeliest": torch.as_tensor(likeliest(cloud, actions)),
            "observed change": resample(observed if len(observed) else cloud),
            "present": resample(cloud),
            "true change": resample(truth),
        }
        for name, points in candidates.items():
            sums[name]["precision"] += _one_way(points, truth)
            sums[name]["coverage"] += _one_way(truth, points)
        count += 1
    if count == 0:
        raise ValueError("no held-out transition where anything newly fills: nothing to measure")
    return {name: {key: value / count for key, value in parts.items()} | {"transitions": count}
            for name, parts in sums.items()}
