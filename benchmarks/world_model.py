"""World-model benchmark (``d2a bench wm``): the paper's Table II on held-out episodes.

For each task: collect (or reuse) expert demonstrations, train the triplane model and the
two ablations (``xy`` plane only, full ``volume``) with the same budget, and report
full-grid and dynamic IoU on held-out episodes next to the persistence baseline, with
parameters, training time and imagination latency per control step, and the Chamfer
distance from the imagined cloud to the true future cloud (as the env serves it, and with
plain voxel-centre decoding) next to that of copying the present. Prints markdown.
"""

from __future__ import annotations

import dataclasses
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from collectors.collect import CollectConfig, collect
from collectors.storage import DemoDataset
from d2a_agents.reward import chamfer_distance
from d2a_agents.world_model.data import WorldModelTransitions
from d2a_agents.world_model.imagine import Imaginer
from d2a_agents.world_model.train import TrainWorldModelConfig, split_episodes, train_world_model
from d2a_agents.world_model.triplane import FEATURE_MODES, WorldModelConfig

PAPER_TRIPLANE_IOU = {"basketball": 92.8, "push": 95.7, "hammer": 94.7, "assembly": 91.9}


@dataclass(frozen=True)
class WorldModelBenchConfig:
    """What ``d2a bench wm`` runs (defaults sized for a 2-core CPU; the paper's grid is 128x128x32)."""

    tasks: tuple[str, ...] = ("hammer", "assembly", "push", "basketball")
    workdir: str = "outputs/bench_wm"
    episodes: int = 10
    model: WorldModelConfig = WorldModelConfig(resolution=(32, 32, 8))
    steps: int = 300
    batch_size: int = 4
    queries: int = 2048
    modes: tuple[str, ...] = FEATURE_MODES
    latency_steps: int = 20
    chamfer_stride: int = 5
    seed: int = 0


def imagination_latency(checkpoint: Path, dataset: DemoDataset, steps: int) -> float:
    """Median seconds of one imagination (voxelize, encode, band decode, FPS) on stored clouds."""
    imaginer = Imaginer.from_checkpoint(checkpoint)
    clouds = dataset.frames()["point_cloud"][:steps]
    actions = torch.zeros(imaginer.config.action_history, imaginer.config.action_dim)
    timings = []
    for cloud in clouds:
        start = time.perf_counter()
        imaginer(cloud, actions)
        timings.append(time.perf_counter() - start)
    return statistics.median(timings)


def imagination_chamfer(
    checkpoint: Path, dataset: DemoDataset, episodes: list[int], stride: int
) -> dict[str, float]:
    """Mean Chamfer distance (m) to the cloud H steps ahead over every ``stride``-th held-out step.

    Keys: ``imagined`` (the env's decoding, observed points kept), ``centres`` (voxel centres
    only) and ``persistence`` (the current cloud itself).
    """
    frames = dataset.frames()
    sums = dict(imagined=0.0, centres=0.0, persistence=0.0)
    decoders = {"imagined": Imaginer.from_checkpoint(checkpoint, keep_observed_points=True),
                "centres": Imaginer.from_checkpoint(checkpoint, keep_observed_points=False)}
    config = decoders["imagined"].config
    transitions = WorldModelTransitions(frames, decoders["imagined"].grid, config.horizon, config.action_history,
                                        episodes)
    positions = range(0, len(transitions), stride)
    for position in positions:
        cloud = torch.as_tensor(frames["point_cloud"][transitions.rows[position]])[:, :3]
        future = torch.as_tensor(frames["point_cloud"][transitions.targets[position]])[:, :3]
        actions = transitions.past_actions(torch.tensor([position]))[0]
        for name, imaginer in decoders.items():
            sums[name] += chamfer_distance(imaginer(cloud, actions), future)
        sums["persistence"] += chamfer_distance(cloud, future)
    return {name: total / len(positions) for name, total in sums.items()}


def run(config: WorldModelBenchConfig = WorldModelBenchConfig()) -> list[dict[str, object]]:
    workdir = Path(config.workdir)
    rows = []
    for task in config.tasks:
        data = workdir / "data" / task
        dataset = DemoDataset.open(data) if DemoDataset.is_dataset(data) else collect(
            CollectConfig(tasks=(task,), out=str(data), episodes=config.episodes, seed=config.seed))
        held_out = split_episodes(dataset, 0.2)[1]
        for mode in config.modes:
            out = workdir / "models" / f"{task}_{mode}.pt"
            start = time.perf_counter()
            model, history = train_world_model(TrainWorldModelConfig(
                data=str(data), out=str(out), model=dataclasses.replace(config.model, feature_mode=mode),
                steps=config.steps, batch_size=config.batch_size, queries=config.queries,
                validate_every=config.steps, validation_stride=1, seed=config.seed, progress=False,
            ))
            seconds = time.perf_counter() - start
            result = history[-1]
            rows.append(dict(
                task=task, mode=mode, full=result.full_iou, dynamic=result.dynamic_iou,
                persistence=result.persistence_full_iou, threshold=result.threshold,
                params=sum(p.numel() for p in model.parameters()), seconds=seconds,
                latency=imagination_latency(out, dataset, config.latency_steps), held_out=len(held_out),
                chamfer=imagination_chamfer(out, dataset, held_out, config.chamfer_stride),
            ))
            print(f"{task} {mode}: full {result.full_iou:.3f} dynamic {result.dynamic_iou:.3f} "
                  f"persistence {result.persistence_full_iou:.3f}", flush=True)
    grid = "x".join(map(str, config.model.resolution))
    print(f"\nHeld-out IoU (%), grid {grid}, {config.steps} steps x batch {config.batch_size}, "
          f"{config.episodes} demos per task (last 20 % held out), threshold chosen on training data, "
          f"pooling {config.model.plane_pooling}; Chamfer to the true future in cm (every "
          f"{config.chamfer_stride}th held-out step): imagined / voxel centres only / copying the present\n")
    print("| task | model | full-grid IoU | dynamic IoU | persistence full-grid | paper triplane | params | "
          "train s | imagine ms/step | Chamfer cm |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for row in rows:
        paper = PAPER_TRIPLANE_IOU.get(row["task"]) if row["mode"] == "triplane" else None
        print(f"| {row['task']} | {row['mode']} | {100 * row['full']:.1f} | {100 * row['dynamic']:.1f} | "
              f"{100 * row['persistence']:.1f} | {'-' if paper is None else paper} | {row['params']} | "
              f"{row['seconds']:.0f} | "
              f"{1000 * row['latency']:.1f} | {100 * row['chamfer']['imagined']:.2f} / "
              f"{100 * row['chamfer']['centres']:.2f} / {100 * row['chamfer']['persistence']:.2f} |")
    return rows


if __name__ == "__main__":
    run()
