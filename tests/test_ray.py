"""Ray: the same episodes, demonstrations and bench cells as a local run, on a local 2-CPU Ray
instance; dead workers retried or reported; a missing install is a clear error."""

from __future__ import annotations

import dataclasses
import functools
import os
import subprocess
import sys

import pytest
import torch

import benchmarks.success as bench
from benchmarks.cells import Cell
from collectors.collect import CollectConfig, collect
from collectors.evaluation import evaluate
from collectors.experts import make_expert
from collectors.ray_jobs import INSTALL_HINT, LOCAL_SYSTEM_CONFIG, JobsLost, Lost, as_completed, import_ray
from collectors.storage import DemoDataset
from d2a.cli import main
from d2a_agents.policy.agent import PolicyConfig
from d2a_agents.policy.checkpoints import load_policy
from d2a_agents.policy.networks import EncoderConfig, VelocityNetConfig
from d2a_agents.policy.train import PolicyPreset

ENV_KWARGS = {"image_size": 48, "num_points": 128}


@pytest.fixture(scope="module")
def ray_instance():
    ray = pytest.importorskip("ray")
    # a small object store: the jobs pass tensordicts of a few MB, and CI's /dev/shm may be small
    ray.init(num_cpus=2, object_store_memory=200 * 1024**2, include_dashboard=False, log_to_driver=False,
             _system_config=LOCAL_SYSTEM_CONFIG)
    yield ray
    ray.shutdown()


def test_a_local_instance_runs_its_jobs_at_the_callers_priority():
    pytest.importorskip("ray")
    # A fresh interpreter, so that the command's own local instance starts (not the fixture's);
    # Ray's default would run the job at niceness 15, behind every other process on the machine.
    code = ("import os\nfrom collectors.ray_jobs import as_completed\n"
            "print([outcome for _, outcome in as_completed(lambda: os.nice(0), [()])][0], os.nice(0))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600, check=True)
    job, caller = map(int, result.stdout.split()[-2:])
    assert job == caller


def test_an_evaluation_on_ray_gives_the_local_episodes(ray_instance):
    expert = functools.partial(make_expert, "reach")
    kwargs = dict(env_kwargs=ENV_KWARGS, max_steps=60, progress=False)
    local = evaluate(expert, "reach", 4, 7, workers=1, **kwargs)
    on_ray = evaluate(expert, "reach", 4, 7, ray_address="local", episodes_per_job=1, **kwargs)
    assert on_ray.workers == 4  # four one-episode jobs
    assert on_ray.seeds == local.seeds == [7, 8, 9, 10]
    assert on_ray.successes == local.successes
    assert on_ray.returns == local.returns and on_ray.lengths == local.lengths
    assert on_ray.success_steps == local.success_steps


def test_a_collection_on_ray_stores_the_local_demonstrations(ray_instance, tmp_path):
    config = CollectConfig(tasks=("reach",), out=str(tmp_path / "local"), episodes=2, max_episode_steps=60,
                           env_kwargs=ENV_KWARGS, progress=False)
    local = collect(config)
    on_ray = collect(dataclasses.replace(config, out=str(tmp_path / "ray"), ray_address="local"))
    assert on_ray.metadata.collections == local.metadata.collections
    assert [e.attempt for e in on_ray.metadata.episodes] == [e.attempt for e in local.metadata.episodes]
    for key in ("point_cloud", "agent_pos", "action"):
        assert torch.equal(on_ray.frames()[key], local.frames()[key]), key
    assert DemoDataset.open(tmp_path / "ray").num_frames == local.num_frames


def test_a_two_cell_bench_on_ray_gives_the_local_cells(ray_instance, tmp_path):
    policy = PolicyConfig(num_points=64, encoder=EncoderConfig(point_widths=(16, 32)),
                          network=VelocityNetConfig(hidden=32, layers=2))
    config = bench.SuccessBenchConfig(
        tasks=("reach",), algos=("mp1",), seeds=(0, 1), demos=2, workdir=str(tmp_path / "local"),
        policy=PolicyPreset(policy, steps=4, batch_size=4, learning_rate=1e-3), evaluations=1, eval_episodes=1,
        final_episodes=2, env_kwargs=ENV_KWARGS, threads=1,
    )
    local = bench.run(config)
    on_ray = bench.run(dataclasses.replace(config, workdir=str(tmp_path / "ray"), ray_address="local"))

    def outcome(cell: Cell) -> tuple:
        return cell.task, cell.algo, cell.seed, cell.periodic, cell.final_wins, cell.final_episodes

    assert [outcome(cell) for cell in on_ray] == [outcome(cell) for cell in local]
    for seed in (0, 1):  # trained alike: the same weights, bit for bit
        run = bench._cell_name(config, "reach", "mp1", seed)
        weights = [load_policy(tmp_path / where / "runs" / run)[0].state_dict() for where in ("local", "ray")]
        assert weights[0].keys() == weights[1].keys()
        assert all(torch.equal(weights[0][key], weights[1][key]) for key in weights[0])
    cells = sorted(p.name for p in (tmp_path / "ray" / "cells").iterdir())
    assert cells == sorted(f"{bench._cell_name(config, 'reach', 'mp1', seed)}.json" for seed in (0, 1))
    # The cells are finished: a rerun on Ray reads them back and starts no job.
    assert bench.run(dataclasses.replace(config, workdir=str(tmp_path / "ray"), ray_address="local")) == on_ray


def test_a_worker_that_dies_is_retried_then_reported_lost(ray_instance, tmp_path):
    marker = tmp_path / "died-once"

    def dies_the_first_time(value: int) -> int:
        if not marker.exists():
            marker.touch()
            os._exit(1)  # the worker process is gone, as when the kernel kills it
        return 2 * value

    assert list(as_completed(dies_the_first_time, [(21,)], max_retries=1)) == [(0, 42)]

    def always_dies() -> None:
        os._exit(1)

    ((index, outcome),) = as_completed(always_dies, [()], max_retries=1)
    assert index == 0 and isinstance(outcome, Lost) and outcome.attempts == 2


def test_an_evaluation_whose_worker_always_dies_names_the_missing_episodes(ray_instance):
    def policy_that_kills_its_worker():
        os._exit(1)

    with pytest.raises(JobsLost, match=r"episode seeds \[5, 6\]"):
        evaluate(policy_that_kills_its_worker, "reach", 2, 5, ENV_KWARGS, max_steps=10, progress=False,
                 ray_address="local")


def test_an_error_raised_by_a_job_reaches_the_caller(ray_instance):
    def divides(value: int) -> float:
        return 1 / value

    with pytest.raises(ZeroDivisionError):
        list(as_completed(divides, [(1,), (0,)]))


def test_without_ray_the_command_says_how_to_install_it(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray now fails, as without the extra
    with pytest.raises(ImportError, match="pip install"):
        import_ray()
    with pytest.raises(SystemExit) as exit_info:
        main(["eval", "--policy", "expert", "--task", "reach", "--episodes", "1", "--ray"])
    assert INSTALL_HINT in str(exit_info.value)
