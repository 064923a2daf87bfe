"""Demonstration collection: end to end, read back, refusal, kill and resume, reproducibility."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

from collectors.atomic import LOCK_NAME, DirectoryBusyError, exclusive_writer
from collectors.collect import CollectConfig, collect
from collectors.storage import METADATA_FILE, DatasetError, DemoDataset
from d2a_envs.wrappers import SeedEachReset
from tests.conftest import SMALL_ENV_KWARGS as ENV_KWARGS


def config(out: Path, **changes) -> CollectConfig:
    return CollectConfig(**{"tasks": ("reach",), "out": str(out), "episodes": 2, "env_kwargs": ENV_KWARGS,
                            "progress": False, **changes})


@pytest.fixture
def reach_dataset(reach_data) -> DemoDataset:
    return DemoDataset.open(reach_data)


def test_collected_episodes_read_back(reach_dataset):
    dataset = DemoDataset.open(reach_dataset.directory)
    assert [e.task for e in dataset.metadata.episodes] == ["reach", "reach"]
    assert dataset.num_frames == 400
    for index in range(2):
        episode = dataset.episode(index)
        assert episode["point_cloud"].shape == (200, 128, 3)
        assert torch.equal(episode["step"], torch.arange(200))
        assert torch.all(episode["episode"] == index)
        assert bool(episode["success"].any())
        assert episode["action"].abs().max() <= 1.0


def test_stored_episode_matches_an_independent_reset(reach_dataset):
    """Episode k of seed s must be what ``reset(seed=s + k)`` gives through Gymnasium."""
    dataset = DemoDataset.open(reach_dataset.directory)
    record = dataset.metadata.episodes[1]
    seed = dataset.metadata.collections[record.collection].seed + record.attempt
    env = gym.make("D2A-MetaWorld-Reach-v0", **ENV_KWARGS)
    observation, _ = env.reset(seed=seed)
    first = dataset.episode(1)[0]
    np.testing.assert_array_equal(first["point_cloud"].numpy(), observation["point_cloud"])
    np.testing.assert_array_equal(first["state"].numpy(), observation["state"])


def test_data_info_describes_the_set(reach_dataset):
    from collectors.storage import describe

    text = describe(DemoDataset.open(reach_dataset.directory))
    assert "2 episodes, 400 steps" in text and "reach" in text and "100%" in text


def test_existing_output_is_refused_without_append_or_overwrite(reach_dataset, tmp_path):
    with pytest.raises(DatasetError, match="--append"):
        collect(config(reach_dataset.directory))
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    with pytest.raises(DatasetError, match="not a D2A data set"):
        collect(config(foreign, overwrite=True))
    with pytest.raises(DatasetError, match="not a D2A data set"):
        collect(config(foreign, append=True))
    assert (foreign / "notes.txt").read_text() == "mine"
    assert [p.name for p in foreign.iterdir()] == ["notes.txt"]  # not even a lock file was left


def test_a_data_set_being_created_by_another_writer_is_busy_not_foreign(tmp_path):
    """Two runs that start one collection together: the second finds the first's lock and its
    metadata not yet renamed into place. It must wait (busy), not refuse the directory as foreign."""
    out = tmp_path / "pool"
    with exclusive_writer(out):  # the first writer, between its lock and its metadata
        (out / f"{METADATA_FILE}.tmp").write_text("{")
        with pytest.raises(DirectoryBusyError):
            collect(config(out, append=True))
        with pytest.raises(DatasetError, match="not a D2A data set"):  # the lock's holder sees no other writer
            DemoDataset.create(out, capacity=10, overwrite=True)
    with pytest.raises(DatasetError, match="not a D2A data set"):  # its writer died there: foreign
        collect(config(out, append=True))
    assert sorted(p.name for p in out.iterdir()) == sorted([LOCK_NAME, f"{METADATA_FILE}.tmp"])


def test_unknown_tasks_are_refused_before_any_file_is_written(tmp_path):
    with pytest.raises(ValueError, match="unknown task"):
        collect(config(tmp_path / "typo", tasks=("reach", "hamer")))
    assert not (tmp_path / "typo").exists()


def test_truncated_and_foreign_directories_get_clear_errors(reach_dataset, tmp_path):
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(reach_dataset.directory, copy)
    shutil.rmtree(copy / "buffer")
    with pytest.raises(DatasetError, match="truncated"):
        DemoDataset.open(copy)
    (copy / METADATA_FILE).write_text("{not json")
    with pytest.raises(DatasetError, match="unreadable"):
        DemoDataset.open(copy)
    with pytest.raises(DatasetError, match="does not exist"):
        DemoDataset.open(tmp_path / "nowhere")


def test_killed_collection_keeps_its_episodes_and_resumes_exactly(tmp_path):
    killed = tmp_path / "killed"
    command = [sys.executable, "-m", "d2a.cli", "collect", "--task", "reach", "--episodes", "3",
               "--out", str(killed), "--image-size", "48", "--num-points", "128"]
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while time.time() < deadline:
        metadata = killed / METADATA_FILE
        if metadata.exists() and len(json.loads(metadata.read_text())["episodes"]) >= 1:
            break
        time.sleep(0.2)
    process.send_signal(signal.SIGKILL)
    process.wait()
    survived = DemoDataset.open(killed)
    assert 1 <= len(survived.metadata.episodes) <= 3
    resumed = collect(config(killed, episodes=3, append=True))
    assert len(resumed.metadata.episodes) == 3
    assert resumed.metadata.collections[0].attempts == 3

    fresh = collect(config(tmp_path / "fresh", episodes=3))
    for key in ("point_cloud", "state", "action"):
        assert torch.equal(resumed.frames()[key], fresh.frames()[key]), key


def test_a_dart_collection_is_allowed_more_attempts_unless_told_otherwise():
    plain = CollectConfig(tasks=("reach",), out="o")
    dart = CollectConfig(tasks=("reach",), out="o", dart_noise=0.05)
    assert (plain.attempts_factor, dart.attempts_factor) == (3, 10)  # the perturbed expert fails more often
    assert CollectConfig(tasks=("reach",), out="o", dart_noise=0.05, max_attempts_factor=2).attempts_factor == 2
    with pytest.raises(ValueError, match="max_attempts_factor must be at least 1"):
        collect(CollectConfig(tasks=("reach",), out="o", max_attempts_factor=0))


def test_seed_each_reset_gives_consecutive_seeds():
    env = SeedEachReset(gym.make("D2A-MetaWorld-Push-v0", **ENV_KWARGS), seed=5)
    seeds, states = [], []
    for _ in range(3):
        observation, info = env.reset()
        seeds.append(info["episode_seed"])
        states.append(observation["state"])
    assert seeds == [5, 6, 7]
    plain = gym.make("D2A-MetaWorld-Push-v0", **ENV_KWARGS)
    np.testing.assert_array_equal(plain.reset(seed=6)[0]["state"], states[1])
    _, info = env.reset(seed=100)
    assert info["episode_seed"] == 100 and env.reset()[1]["episode_seed"] == 101


def test_an_episode_is_committed_with_its_count(tmp_path, monkeypatch):
    """A collection killed right after an episode's metadata write (before any later save)
    resumes without storing that episode twice: the episode and the kept count are one write."""

    def killed(self):
        raise KeyboardInterrupt  # the process dies before the next metadata save

    monkeypatch.setattr(DemoDataset, "commit", killed)
    with pytest.raises(KeyboardInterrupt):
        collect(config(tmp_path / "data", episodes=1))
    monkeypatch.undo()
    on_disk = DemoDataset.open(tmp_path / "data").metadata
    assert len(on_disk.episodes) == 1 and on_disk.collections[0].kept == 1
    assert len(collect(config(tmp_path / "data", episodes=1, append=True)).metadata.episodes) == 1


def test_bad_settings_are_refused_before_an_existing_data_set_is_touched(reach_dataset, tmp_path):
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(reach_dataset.directory, copy)
    before = (copy / METADATA_FILE).read_text()
    bad = config(copy, overwrite=True, env_kwargs={**ENV_KWARGS, "num_points": 0})
    with pytest.raises(ValueError, match="num_points"):
        collect(bad)
    assert (copy / METADATA_FILE).read_text() == before
    assert len(DemoDataset.open(copy).metadata.episodes) == len(reach_dataset.metadata.episodes)
    held = config(tmp_path / "held", tasks=("adroit-pen",), env_kwargs={**ENV_KWARGS, "action_repeat": 2},
                  expert="planner")
    with pytest.raises(ValueError, match="wrong pace"):  # the planner plans one action per simulator step
        collect(held)
    assert not (tmp_path / "held").exists()


def test_images_are_stored_per_step_and_replay_to_the_same_view(tmp_path):
    """A collection with ``rgb_image_size`` stores every step's image: replaying the episode's
    seed and actions through Gymnasium shows the same images; a data set holds images in every
    episode or in none."""
    from collectors.storage import EpisodeRecord

    env_kwargs = {**ENV_KWARGS, "rgb_image_size": 40}
    collect(config(tmp_path / "images", episodes=1, env_kwargs=env_kwargs, max_episode_steps=12, keep_failures=True))
    dataset = DemoDataset.open(tmp_path / "images")
    assert "image" in dataset.frame_keys
    episode = dataset.episode(0)
    assert episode["image"].shape == (12, 40, 40, 3) and episode["image"].dtype == torch.uint8
    env = gym.make("D2A-MetaWorld-Reach-v0", **env_kwargs)
    observation, _ = env.reset(seed=dataset.metadata.collections[0].seed)
    for step in range(12):
        np.testing.assert_array_equal(episode["image"][step].numpy(), observation["image"])
        observation = env.step(episode["action"][step].numpy())[0]
    without = episode.exclude("image")
    record = EpisodeRecord(index=1, task="reach", start=0, length=0, success=False, episode_return=0.0,
                           collection=0, attempt=1, min_points_in_crop=128)
    with pytest.raises(DatasetError, match="images are stored in every episode"):
        dataset.add_episode(without, record)
    plain = DemoDataset.create(tmp_path / "plain", capacity=12)
    plain.add_episode(without, record)
    assert plain.frame_keys == DemoDataset.open(tmp_path / "plain").frame_keys  # no image key
    assert "image" not in plain.frame_keys


def test_a_truncated_image_file_is_refused(tmp_path):
    collect(config(tmp_path / "images", episodes=1, env_kwargs={**ENV_KWARGS, "rgb_image_size": 40},
                   max_episode_steps=4, keep_failures=True))
    images = tmp_path / "images" / "buffer" / "storage" / "image.memmap"
    with open(images, "r+b") as handle:
        handle.truncate(images.stat().st_size // 2)
    with pytest.raises(DatasetError, match="image.memmap holds"):
        DemoDataset.open(tmp_path / "images")
