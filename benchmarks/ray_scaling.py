"""Ray scaling (``d2a bench ray``): the same small ``bench success`` grid on 1 and on 2 Ray CPUs.

The demonstrations are collected once, before any timing, and shared by the runs; each run
then gets a fresh workdir (nothing to resume), a fresh local Ray instance with ``cpus`` CPUs
and the whole grid as Ray jobs of one CPU each. Its wall time counts the Ray start-up, the
workers' imports and every cell's training and evaluations. Printed: a markdown table of
the wall times, the speed-up over the first row, and whether every run's cells equal the
first run's (they must: the jobs are seeded, not scheduled).
"""

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

from benchmarks.cells import Cell
from benchmarks.success import SuccessBenchConfig
from benchmarks.success import run as run_bench
from collectors.collect import CollectConfig, collect
from collectors.ray_jobs import LOCAL, import_ray, ray_cluster
from d2a_agents.policy.train import POLICY_PRESETS, PolicyPreset


@dataclass(frozen=True)
class RayScalingConfig:
    """What ``d2a bench ray`` runs: ``seeds`` cells of ``algo`` on ``task``, once per entry of ``cpus``."""

    task: str = "reach"
    algo: str = "mp1"
    seeds: tuple[int, ...] = (0, 1, 2, 3)
    cpus: tuple[int, ...] = (1, 2)
    demos: int = 5
    # the cpu preset's networks, a short budget: each cell is about a minute on one core
    policy: PolicyPreset = dataclasses.replace(POLICY_PRESETS["cpu"], steps=300)
    evaluations: int = 1
    eval_episodes: int = 10
    final_episodes: int = 20
    workdir: str = "outputs/bench_ray"
    env_kwargs: dict[str, object] = field(default_factory=dict)


def _outcomes(cells: list[Cell]) -> list[tuple]:
    return [(c.task, c.algo, c.seed, c.periodic, c.final_wins, c.final_episodes) for c in cells]


def run(config: RayScalingConfig = RayScalingConfig()) -> list[dict[str, object]]:
    """Time the grid on each CPU count; prints the table and returns its rows."""
    if import_ray().is_initialized():
        raise ValueError("bench ray starts its own Ray instances: call it without a Ray connection")
    workdir = Path(config.workdir)
    data = workdir / "data" / config.task
    # Collected once and shared by every run; a collection cut short is completed.
    collect(CollectConfig(tasks=(config.task,), out=str(data), episodes=config.demos, env_kwargs=config.env_kwargs,
                          append=True))
    rows: list[dict[str, object]] = []
    for cpus in config.cpus:
        run_dir = workdir / f"cpus{cpus}_{time.strftime('%Y%m%d-%H%M%S')}"
        (run_dir / "data").mkdir(parents=True)
        (run_dir / "data" / config.task).symlink_to(data.resolve(), target_is_directory=True)
        bench = SuccessBenchConfig(
            tasks=(config.task,), algos=(config.algo,), seeds=config.seeds, demos=config.demos,
            workdir=str(run_dir), policy=config.policy, evaluations=config.evaluations,
            eval_episodes=config.eval_episodes, final_episodes=config.final_episodes,
            env_kwargs=config.env_kwargs, threads=1, ray_address="local",
        )
        load = os.getloadavg()[0]
        start = time.perf_counter()
        with ray_cluster(LOCAL, num_cpus=cpus):  # the bench's jobs use this instance
            cells = run_bench(bench)
        rows.append(dict(cpus=cpus, seconds=time.perf_counter() - start, load=load, outcomes=_outcomes(cells)))
    print(f"\n{len(config.seeds)} cells ({config.algo} on {config.task}, {config.policy.steps} steps x batch "
          f"{config.policy.batch_size}, {config.evaluations} evaluation(s) of {config.eval_episodes} + "
          f"{config.final_episodes} final episodes), one CPU and one torch thread per cell, "
          f"{os.cpu_count()} cores on this machine\n")
    print("| Ray CPUs | wall time (s) | speed-up | same cells as the first row | 1-min load before |")
    print("| --- | --- | --- | --- | --- |")
    for row in rows:
        print(f"| {row['cpus']} | {row['seconds']:.1f} | {rows[0]['seconds'] / row['seconds']:.2f}x | "
              f"{row['outcomes'] == rows[0]['outcomes']} | {row['load']:.1f} |")
    return rows
