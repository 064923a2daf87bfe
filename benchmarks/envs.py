"""Environment throughput: steps per second of each depth backend vs. state-only Meta-World.

Every configuration runs the same whole-episode loop (reset, then random actions) in one
process, one after the other, so that the ratios are measured side by side.
"""

from __future__ import annotations

import itertools
import os
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from functools import partial

import gymnasium as gym
import numpy as np

import d2a_envs
from d2a_envs.camera import camera_id
from d2a_envs.depth import RaycastDepth, RenderDepth
from d2a_envs.suites.metaworld import MetaWorldEnv


@dataclass(frozen=True)
class EnvBenchConfig:
    """What ``d2a bench envs`` measures."""

    task: str = "hammer"
    steps: int = 100
    seed: int = 0
    backends: tuple[str, ...] = ("raycast", "render")
    image_sizes: tuple[int, ...] = (84, 128)
    point_counts: tuple[int, ...] = (512, 1024)
    vector_processes: int = 2
    agreement_tasks: tuple[str, ...] = ("hammer", "assembly", "push", "basketball")
    agreement_cameras: tuple[str, ...] = ("corner4", "corner2", "topview")
    render_rounds: int = 6  # the llvmpipe thread comparison: alternating runs of each setting
    render_image_size: int = 256  # ... at the grids' clouds (256-px depth, 4096 points)
    render_points: int = 4096


def steps_per_second(env: gym.Env, steps: int, seed: int) -> float:
    """Run ``steps`` random steps after a reset (reset not timed); resets again on episode end."""
    env.reset(seed=seed)
    env.action_space.seed(seed)
    actions = [env.action_space.sample() for _ in range(steps)]
    start = time.perf_counter()
    for action in actions:
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset()
    return steps / (time.perf_counter() - start)


def vector_steps_per_second(env_id: str, backend: str, processes: int, steps: int, seed: int) -> float:
    """Env steps per second of an ``AsyncVectorEnv`` with one env per process (128 px, N = 1024).

    Workers are spawned, not forked (this process has already rendered, and GL does not
    survive a fork); the ``d2a_envs:`` prefix makes each fresh worker register the ids.
    """
    envs = gym.vector.AsyncVectorEnv(
        [partial(gym.make, f"d2a_envs:{env_id}", backend=backend) for _ in range(processes)], context="spawn"
    )
    envs.reset(seed=[seed + i for i in range(processes)])
    envs.action_space.seed(seed)
    actions = [envs.action_space.sample() for _ in range(steps)]
    envs.step(actions[0])  # let every worker create its renderer before timing
    start = time.perf_counter()
    for action in actions:
        envs.step(action)
    rate = processes * steps / (time.perf_counter() - start)
    envs.close()
    return rate


def backend_agreement(config: EnvBenchConfig) -> None:
    """Print, per task and camera, the share of pixels seen by both backends whose depths
    differ by less than 2 mm (128 px, after 10 random steps)."""
    print("\n| task | camera | pixels seen by both | depth within 2 mm | seen by one only |")
    print("| --- | --- | --- | --- | --- |")
    for task, camera in itertools.product(config.agreement_tasks, config.agreement_cameras):
        env = gym.make(d2a_envs.get_task(task).env_id, image_size=16, num_points=8)
        env.reset(seed=config.seed)
        env.action_space.seed(config.seed)
        for _ in range(10):
            env.step(env.action_space.sample())
        model, data = env.unwrapped.model, env.unwrapped.data
        cam = camera_id(model, camera)
        ray = RaycastDepth(128, 128).capture(model, data, cam, with_rgb=False).depth
        render = RenderDepth(128, 128).capture(model, data, cam, with_rgb=False).depth
        both = np.isfinite(ray) & np.isfinite(render)
        within = np.mean(np.abs(ray[both] - render[both]) < 0.002)
        one = np.mean(np.isfinite(ray) ^ np.isfinite(render))
        print(f"| {task} | {camera} | {both.sum()} | {100 * within:.2f} % | {100 * one:.2f} % |")
        env.close()


def render_thread_comparison(config: EnvBenchConfig) -> dict[str, float]:
    """Median ms per ``render`` step with llvmpipe's own thread pool (``LP_NUM_THREADS`` unset) and
    drawing in the calling thread (``0``, what ``software_render_threads(1)`` picks), each in a fresh
    process (Mesa reads the variable once), alternating over ``render_rounds`` rounds so that both
    meet the same load; prints each round and the medians."""
    script = ("import sys, gymnasium as gym, d2a_envs\n"
              "from benchmarks.envs import steps_per_second\n"
              f"env = gym.make({d2a_envs.get_task(config.task).env_id!r}, backend='render', "
              f"image_size={config.render_image_size}, num_points={config.render_points})\n"
              f"steps_per_second(env, 5, {config.seed})  # the GL context and first frames, not timed\n"
              f"print(1000 / steps_per_second(env, {config.steps}, {config.seed}))\n")
    settings = {"llvmpipe's pool (unset)": None, "calling thread (0)": "0"}
    times: dict[str, list[float]] = {name: [] for name in settings}
    print(f"\n{config.task}, render backend, {config.render_image_size} px, {config.render_points} points, "
          f"{config.steps} steps per run, torch and OpenMP at one thread")
    for round_index, (name, value) in itertools.product(range(config.render_rounds), settings.items()):
        env = {key: item for key, item in os.environ.items() if key != "LP_NUM_THREADS"} | {"OMP_NUM_THREADS": "1"}
        env |= {"LP_NUM_THREADS": value} if value is not None else {}
        finished = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, check=True)
        times[name].append(float(finished.stdout.split()[-1]))
        print(f"  round {round_index + 1}, {name}: {times[name][-1]:.1f} ms/step", flush=True)
    medians = {name: statistics.median(values) for name, values in times.items()}
    pool, calling = medians.values()
    print("| LP_NUM_THREADS | median ms/step |\n| --- | --- |")
    for name, median in medians.items():
        print(f"| {name} | {median:.1f} |")
    print(f"calling thread / pool: {calling / pool:.2f}x the time")
    return medians


def run(config: EnvBenchConfig = EnvBenchConfig()) -> list[dict[str, object]]:
    """Measure every configuration; returns rows and prints a markdown table."""
    spec = d2a_envs.get_task(config.task)
    reference_env = gym.wrappers.TimeLimit(MetaWorldEnv(spec.task), d2a_envs.DEFAULT_MAX_EPISODE_STEPS)
    reference = steps_per_second(reference_env, config.steps, config.seed)
    rows: list[dict[str, object]] = [dict(env="state-only Meta-World", size="-", points="-", sps=reference)]
    for backend, size, points in itertools.product(config.backends, config.image_sizes, config.point_counts):
        try:
            env = gym.make(spec.env_id, backend=backend, image_size=size, num_points=points)
        except RuntimeError as error:  # no GL library for the render backend
            print(f"skipping {backend}: {error}")
            break
        rate = steps_per_second(env, config.steps, config.seed)
        rows.append(dict(env=f"D2A {backend}", size=size, points=points, sps=rate))
        env.close()
    print(f"\n{spec.env_id}, {config.steps} steps per row, one process\n")
    print("| env | image | N | steps/s | x state-only |")
    print("| --- | --- | --- | --- | --- |")
    for row in rows:
        print(f"| {row['env']} | {row['size']} | {row['points']} | {row['sps']:.1f} | {row['sps'] / reference:.3f} |")
    by_key = {(r["env"], r["size"], r["points"]): r["sps"] for r in rows}
    fast, slow = by_key.get(("D2A raycast", 128, 1024)), by_key.get(("D2A render", 128, 1024))
    if fast and slow:
        print(f"\nraycast / render at 128 px, N = 1024: {fast / slow:.2f}x")
        print(f"\nAsyncVectorEnv, {config.vector_processes} processes, 128 px, N = 1024 (env steps/s):")
        for backend in config.backends:
            rate = vector_steps_per_second(
                spec.env_id, backend, config.vector_processes, config.steps // 2, config.seed
            )
            print(f"  {backend}: {rate:.1f}")
        backend_agreement(config)
    return rows


if __name__ == "__main__":
    run()
