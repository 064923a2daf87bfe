"""DAgger: a student acts, the expert labels the states it reaches, the labelled episodes train."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from benchmarks.dagger import DAGGER_SEED, DaggerConfig, run_task
from benchmarks.experts import ExpertBenchConfig
from collectors.collect import CollectConfig, collect
from collectors.experts import ExpertSettings, Student
from collectors.storage import DatasetError, DemoDataset

SMALL = {"image_size": 32, "num_points": 32}


class Drift(TensorDictModuleBase):
    """A student that moves the hand down and sideways at a constant speed, whatever it sees (so
    every step reaches a new state), and checks that the env marks where episodes start."""

    in_keys = ["is_init"]
    out_keys = ["action"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        assert tensordict.get("is_init").dtype == torch.bool
        tensordict.set("action", torch.tensor([0.3, 0.0, -0.3, 0.0]))
        return tensordict


DRIFT = Student("drift", Drift)


def test_the_student_acts_and_the_expert_labels_each_state_it_reaches(tmp_path):
    """The stored actions are the scripted expert's own in the stored states (recomputed here),
    step for step, while the hand goes where the student's constant action drives it."""
    from metaworld.policies import ENV_POLICY_MAP

    out = tmp_path / "dagger"
    collect(CollectConfig(tasks=("reach",), out=str(out), episodes=2, env_kwargs=SMALL, student=DRIFT,
                          max_episode_steps=30, progress=False))
    dataset = DemoDataset.open(out)
    record = dataset.metadata.collections[0]
    assert record.student == "drift" and record.attempts == 2 and record.kept == 2  # failures kept
    assert not any(e.success for e in dataset.metadata.episodes)
    assert dataset.rollout_episodes() == [] and dataset.demonstrations() is dataset  # labelled: training data
    episode = dataset.episode(0)
    expert = ENV_POLICY_MAP["reach-v3"]()
    labels = np.stack([np.clip(expert.get_action(state), -1, 1) for state in episode["state"].double().numpy()])
    np.testing.assert_allclose(episode["action"].numpy(), labels, atol=1e-5)
    assert np.abs(episode["action"][1:].numpy() - labels[:-1]).max() > 1e-3  # so a label one step off would show
    hand = episode["state"][:, :3].numpy()
    steps = np.diff(hand, axis=0)
    assert (steps[5:, 0] > 0).all() and (steps[5:, 2] < 0).all()  # the student drove: +x and -z every step


def test_without_labels_the_students_own_actions_are_stored_as_rollouts(tmp_path):
    """``student_labels=False`` (``d2a collect --policy``): the expert does not label, every step
    stores the action the student executed, and the episodes are rollouts that no policy trains on."""
    out = tmp_path / "own"
    collect(CollectConfig(tasks=("reach",), out=str(out), episodes=2, env_kwargs=SMALL, student=DRIFT,
                          student_labels=False, max_episode_steps=10, progress=False))
    dataset = DemoDataset.open(out)
    record = dataset.metadata.collections[0]
    assert (record.student, record.student_labels, record.kept) == ("drift", False, 2)
    np.testing.assert_array_equal(dataset.frames()["action"].numpy(), np.tile(np.float32([0.3, 0, -0.3, 0]), (20, 1)))
    assert dataset.rollout_episodes() == [0, 1]
    with pytest.raises(DatasetError, match="labelled: False"):  # a labelled collection does not resume it
        collect(CollectConfig(tasks=("reach",), out=str(out), episodes=3, append=True, env_kwargs=SMALL,
                              student=DRIFT, max_episode_steps=10, progress=False))
    with pytest.raises(ValueError, match="give the student"):
        ExpertSettings(student_labels=False)


def test_a_student_collection_resumes_only_with_the_same_student(tmp_path):
    out = str(tmp_path / "dagger")
    collect(CollectConfig(tasks=("reach",), out=out, episodes=1, env_kwargs=SMALL, student=DRIFT,
                          max_episode_steps=10, progress=False))
    with pytest.raises(DatasetError, match="student drift"):
        collect(CollectConfig(tasks=("reach",), out=out, episodes=2, append=True, env_kwargs=SMALL,
                              max_episode_steps=10, progress=False))


def test_a_student_excludes_noise():
    with pytest.raises(ValueError, match="and a student"):
        ExpertSettings(dart_noise=0.1, student=DRIFT)


def test_dagger_refuses_what_it_cannot_run():
    with pytest.raises(ValueError, match="imitation_demos must be at least 1"):
        DaggerConfig(check=ExpertBenchConfig(imitation_demos=0))
    with pytest.raises(ValueError, match="would reach the check's layouts"):
        DaggerConfig(rounds=10)


def test_each_round_trains_on_the_last_students_labelled_episodes_and_resumes(tmp_path):
    check = ExpertBenchConfig(tasks=("reach",), env_kwargs=SMALL, workers=1, imitation_demos=1,
                              imitation_episodes=1, imitation_steps=2, workdir=str(tmp_path))
    config = DaggerConfig(check=check, rounds=1, episodes_per_round=1)
    rounds = run_task(config, "reach")
    assert [(r.index, r.episodes) for r in rounds] == [(0, 1), (1, 2)]
    assert rounds[0].collected is None and rounds[1].collected[1] == 1
    dataset = DemoDataset.open(tmp_path / "data" / "reach_dagger")
    student = dataset.metadata.collections[1]
    assert student.seed == DAGGER_SEED and student.student == str((rounds[0].run / "policy.pt").resolve())
    again = run_task(config, "reach")  # read back: nothing collected or trained again
    assert [r.score.successes for r in again] == [r.score.successes for r in rounds]
    assert len(DemoDataset.open(tmp_path / "data" / "reach_dagger").metadata.episodes) == 2
