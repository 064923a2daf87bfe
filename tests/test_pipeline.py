"""Short end-to-end paths: collect -> train a few steps -> evaluate, for the policy variants."""

from __future__ import annotations

import copy
import dataclasses
import json
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from collectors.evaluation import evaluate
from collectors.storage import DatasetError, DemoDataset
from d2a_agents.checkpoint import CheckpointError, file_sha256, load_checkpoint, save_checkpoint
from d2a_agents.policy.agent import PolicyConfig
from d2a_agents.policy.checkpoints import (
    CHECKPOINT_NAME,
    Acting,
    eval_env_kwargs,
    evaluate_checkpoint,
    load_policy,
    load_torchrl_policy,
)
from d2a_agents.policy.networks import EncoderConfig, VelocityNetConfig
from d2a_agents.policy.report import read_run
from d2a_agents.policy.train import POLICY_PRESETS, TrainPolicyConfig, train_policy
from d2a_agents.world_model.train import TrainWorldModelConfig, train_world_model
from d2a_agents.world_model.triplane import WorldModelConfig

# Image widths off their default, as the cpu preset's: a cloud policy's checkpoint drops them.
TINY = dict(num_points=64, encoder=EncoderConfig(point_widths=(16, 32), image_widths=(8, 8, 8, 8)),
            network=VelocityNetConfig(hidden=32, layers=2))


@pytest.fixture(scope="module")
def world_model(reach_data, tmp_path_factory) -> str:
    out = tmp_path_factory.mktemp("wm") / "wm.pt"
    model = WorldModelConfig(resolution=(16, 16, 8))
    train_world_model(TrainWorldModelConfig(data=reach_data, out=str(out), model=model, steps=2, batch_size=2,
                                            queries=256, validate_every=2, validation_stride=20, progress=False))
    return str(out)


def frames_kept_by_the_cpu_preset(data: str, episodes: list[int] | None = None) -> int:
    """Frames up to 10 past each episode's first success (the cpu preset's trimming), counted by hand."""
    frames = DemoDataset.open(data).frames()
    success, episode = np.asarray(frames["success"]).reshape(-1), np.asarray(frames["episode"]).reshape(-1)
    kept = 0
    for index in np.unique(episode) if episodes is None else episodes:
        hits = np.flatnonzero(success[episode == index])
        kept += min(int((episode == index).sum()), int(hits[0]) + 11) if len(hits) else int((episode == index).sum())
    return kept


def policy_config(algo: str, data: str, out, world_model: str | None = None, steps: int = 3) -> TrainPolicyConfig:
    return TrainPolicyConfig(data=data, out=str(out), policy=PolicyConfig(algo=algo, **TINY),
                             world_model=world_model, steps=steps, batch_size=4, eval_episodes=1, checkpoint_every=2,
                             progress=False)


def test_a_consistency_student_distils_its_edm_teacher_and_reads_as_it_does(reach_data, tmp_path):
    """--algo cp: the teacher's normalizers and encoder, frozen, and its network as the target's ODE;
    the student acts in one network evaluation; a teacher of another kind is refused."""
    train_policy(policy_config("edm", reach_data, tmp_path / "teacher"))
    teacher, _ = load_policy(tmp_path / "teacher")
    config = dataclasses.replace(policy_config("edm", reach_data, tmp_path / "student"),
                                 policy=PolicyConfig(algo="cp", **TINY), teacher=str(tmp_path / "teacher"))
    student, _ = train_policy(config)
    for name, value in teacher.encoder.state_dict().items():
        assert torch.equal(student.encoder.state_dict()[name], value)  # frozen through training and the EMA
    assert torch.equal(student.normalizers["action"].low, teacher.normalizers["action"].low)
    payload = load_checkpoint(tmp_path / "student" / CHECKPOINT_NAME, "policy")
    assert payload["teacher_sha256"] == file_sha256(tmp_path / "teacher" / CHECKPOINT_NAME)
    calls = []
    student.net.register_forward_hook(lambda *_: calls.append(1))
    window = {key: torch.zeros(1, 2, *shape) for key, shape in (("point_cloud", (8, 3)), ("agent_pos", (4,)))}
    student.predict_action_chunk(window)
    assert len(calls) == 1
    with pytest.raises(CheckpointError, match="distils an edm"):
        train_policy(dataclasses.replace(config, out=str(tmp_path / "other"), teacher=str(tmp_path / "student")))
    with pytest.raises(ValueError, match="needs one"):
        policy_config("cp", reach_data, tmp_path / "no-teacher")
    with pytest.raises(ValueError, match="goes with --algo cp"):
        dataclasses.replace(policy_config("mp1", reach_data, tmp_path / "mp1"), teacher=str(tmp_path / "teacher"))


@pytest.mark.parametrize("algo, normalizers", [
    ("mp1", {"action", "agent_pos", "point_cloud"}), ("dp3", {"action", "agent_pos", "point_cloud"}),
    ("flowpolicy", {"action", "agent_pos", "point_cloud"}), ("edm", {"action", "agent_pos", "point_cloud"}),
    ("mp1-state", {"action", "state"}),
])
def test_collect_train_evaluate_without_imagination(algo, normalizers, reach_data, tmp_path):
    _, history = train_policy(policy_config(algo, reach_data, tmp_path))
    assert [point.step for point in history] == [3] and history[0].episodes == 1
    payload = load_checkpoint(tmp_path / CHECKPOINT_NAME, "policy")
    assert {key.split(".")[1] for key in payload["ema"] if key.startswith("normalizers.")} == normalizers
    (check,) = payload["reliance"]  # the perception check ran once, at the end, on training windows
    assert check["step"] == 3 and check["where"] == "training"
    assert check["windows"] == frames_kept_by_the_cpu_preset(reach_data) < 400  # of 2 x 200 frames
    assert (check["clouds_shuffled"] is None) == (algo == "mp1-state")
    (outcome,) = read_run(tmp_path)  # what d2a report reads of a real run
    assert (outcome.task, outcome.algo, outcome.episodes, outcome.wins) == ("reach", algo, 1, history[0].success_rate)
    assert set(outcome.reliance) == ({"state"} if algo == "mp1-state" else {"clouds", "state"})
    assert [set(row) for row in payload["metrics"]] == [{"step", "mse"}] * 3  # no CFG gate in these variants
    logged = tmp_path / "logs" / algo / "scalars"  # the same figures, as TorchRL's CSV logger writes them
    assert (logged / "train" / "mse.csv").read_text().splitlines()[-1].startswith("3,")
    assert (logged / "success" / "reach.csv").is_file() and (logged / "reliance" / "state.csv").is_file()
    result = evaluate(lambda: load_torchrl_policy(tmp_path / CHECKPOINT_NAME), "reach", 1, seed=5,
                      env_kwargs=eval_env_kwargs(payload, "reach"), progress=False)
    assert len(result.successes) == 1 and len(result.returns) == 1
    with pytest.raises(ValueError, match="trained on"):
        evaluate_checkpoint(tmp_path / CHECKPOINT_NAME, "hammer", 1, seed=0)
    with pytest.raises(ValueError, match="trained on"):  # a run directory names its policy.pt
        evaluate_checkpoint(tmp_path, "hammer", 1, seed=0)


def test_d2a_trains_on_imagined_clouds_and_acts_with_them(reach_data, world_model, tmp_path):
    policy, history = train_policy(policy_config("d2a", reach_data, tmp_path, world_model=world_model))
    assert policy.config.encoder.use_imagination
    payload = load_checkpoint(tmp_path / CHECKPOINT_NAME, "policy")
    # acts with imagination, from the world model's absolute path (any working directory)
    assert eval_env_kwargs(payload, "reach")["world_model"] == str(Path(world_model).resolve())
    assert "imagined_output" not in eval_env_kwargs(payload, "reach")  # the future cloud: the env's default
    gate = [(row["cfg_weight"], row["cfg_rho"], row["cfg_active"]) for row in payload["metrics"]]
    assert len(gate) == 3 and all(0 <= w <= 1 and -1 <= rho <= 1 and 0 <= active <= 1 for w, rho, active in gate)
    assert history[0].episodes == 1
    assert_the_steps_it_skips_change_nothing(tmp_path)
    assert_its_rollouts_skip_the_imagination_it_does_not_read(tmp_path, tmp_path / "rollouts")


def test_an_env_refuses_to_imagine_from_a_cloud_it_skips(world_model):
    import d2a_envs
    from d2a_envs.wrappers import IMAGINED_KEY

    with pytest.raises(ValueError, match="imagines from the present cloud"):
        d2a_envs.make_env("metaworld", "reach-v3", world_model=world_model, image_size=48, num_points=128,
                          read_steps={"point_cloud": (3, 1), IMAGINED_KEY: (3, 2)})


def assert_the_steps_it_skips_change_nothing(run: Path) -> None:
    """An evaluation that renders and imagines only the steps the policy reads plays the same
    episodes as one that makes every step's clouds (returns sum every step's reward: the same
    actions throughout)."""
    skipped, every = (evaluate_checkpoint(run, "reach", 1, seed=5, progress=False, skip_unread=skip)
                      for skip in (True, False))
    assert (skipped.successes, skipped.lengths, skipped.returns) == (every.successes, every.lengths, every.returns)


def assert_its_rollouts_skip_the_imagination_it_does_not_read(run: Path, out: Path) -> None:
    """A collection of the policy's own rollouts (``d2a collect --policy``) imagines only at the
    steps the policy reads, renders the stored cloud at every step, and stores the same episode,
    frame for frame, as a collection that imagines at every step."""
    from collectors.collect import CollectConfig, collect
    from d2a_agents.policy.checkpoints import checkpoint_student, trained_env_kwargs
    from d2a_envs.read_steps import ReadSteps
    from d2a_envs.wrappers import IMAGINED_KEY

    frames = []
    for skip in (True, False):
        student = checkpoint_student(run, "reach", skip_unread=skip)
        assert student.env_kwargs.get("read_steps") == ({IMAGINED_KEY: ReadSteps(3, 1)} if skip else None)
        stored = trained_env_kwargs(run, "reach")
        collect(CollectConfig(tasks=("reach",), out=str(out / f"skip{skip}"), episodes=1, env_kwargs=stored,
                              student=student, student_labels=False, max_episode_steps=14, progress=False))
        frames.append(DemoDataset.open(out / f"skip{skip}").frames())
    skipped, every = frames
    assert skipped["point_cloud"].shape[0] == 14 and not skipped["point_cloud"].isnan().any()
    for key in ("point_cloud", "agent_pos", "state", "action"):
        assert torch.equal(skipped[key], every[key]), key


def test_bench_eval_times_both_settings_and_a_policy_refuses_a_cloud_its_env_skipped(reach_data, tmp_path, capsys):
    from benchmarks.evaluation_speed import EvaluationSpeedConfig
    from benchmarks.evaluation_speed import run as bench_eval
    from d2a_envs.read_steps import ReadSteps
    from d2a_envs.wrappers import IMAGINED_KEY

    train_policy(policy_config("mp1", reach_data, tmp_path, steps=1))
    timings = bench_eval(EvaluationSpeedConfig(policy=str(tmp_path), task="reach", episodes=1, rounds=1))
    assert {name: len(rounds) for name, rounds in timings.items()} == {"every step": 1, "steps read": 1}
    assert all(ms > 0 for rounds in timings.values() for ms in rounds)
    printed = capsys.readouterr().out
    assert "the same in both settings" in printed and "| steps read |" in printed
    payload = load_checkpoint(tmp_path / CHECKPOINT_NAME, "policy")
    config = PolicyConfig.from_dict(payload["policy_config"])  # plans every 3 steps from the last 2 observations
    assert config.read_steps() == {"point_cloud": ReadSteps(3, 2)}
    assert PolicyConfig(algo="d2a").read_steps() == {"point_cloud": ReadSteps(3, 2), IMAGINED_KEY: ReadSteps(3, 1)}
    assert PolicyConfig(algo="mp1-state", n_action_steps=1).read_steps() == {"point_cloud": ReadSteps(1, 0)}
    kwargs = {**eval_env_kwargs(payload, "reach"), "read_steps": {"point_cloud": ReadSteps(3, 1)}}  # one short
    with pytest.raises(ValueError, match="skipped a point_cloud this policy reads"):
        evaluate(lambda: load_torchrl_policy(tmp_path / CHECKPOINT_NAME), "reach", 1, seed=5, env_kwargs=kwargs,
                 progress=False)


def test_d2a_change_trains_and_acts_on_the_voxels_its_world_model_fills(reach_data, world_model, tmp_path):
    import gymnasium as gym

    from d2a_envs.wrappers import IMAGINED_KEY

    _, history = train_policy(policy_config("d2a-change", reach_data, tmp_path, world_model=world_model))
    assert history[0].episodes == 1
    kwargs = eval_env_kwargs(load_checkpoint(tmp_path / CHECKPOINT_NAME, "policy"), "reach")
    assert kwargs["imagined_output"] == "change"
    env = gym.make("D2A-MetaWorld-Reach-v0", **kwargs)
    observation, _ = env.reset(seed=0)
    grid = env.get_wrapper_attr("imaginer").grid
    now = grid.voxelize(torch.as_tensor(observation["point_cloud"]))
    voxels, inside = grid.indices(torch.as_tensor(observation[IMAGINED_KEY]))
    assert observation[IMAGINED_KEY].shape == (64, 3) and inside.all()
    assert not now[tuple(voxels.T)].any()  # every imagined point lies in a voxel empty now
    env.close()


def test_a_policy_refuses_a_world_model_swapped_after_training(reach_data, world_model, tmp_path):
    own = tmp_path / "wm.pt"
    shutil.copy(world_model, own)
    train_policy(policy_config("d2a", reach_data, tmp_path / "run", world_model=str(own), steps=1))
    payload = load_checkpoint(tmp_path / "run" / CHECKPOINT_NAME, "policy")
    with open(own, "ab") as handle:
        handle.write(b"another model")  # same path, other bytes
    with pytest.raises(CheckpointError, match="has changed"):
        eval_env_kwargs(payload, "reach")
    own.unlink()
    with pytest.raises(CheckpointError, match="missing"):
        eval_env_kwargs(payload, "reach")


def test_held_out_episodes_are_not_trained_on_and_serve_the_perception_check(reach_data, tmp_path):
    config = dataclasses.replace(policy_config("mp1", reach_data, tmp_path), holdout_episodes=1, eval_episodes=0)
    train_policy(config)
    payload = load_checkpoint(tmp_path / CHECKPOINT_NAME, "policy")
    assert payload["held_out_episodes"] == [1]
    assert payload["reliance"][0]["where"] == "held-out"
    assert payload["reliance"][0]["windows"] == frames_kept_by_the_cpu_preset(reach_data, [1])
    with pytest.raises(ValueError, match="cannot hold out 2 of 2"):
        train_policy(dataclasses.replace(config, out=str(tmp_path / "other"), holdout_episodes=2))


def test_bad_training_settings_are_refused():
    for field, value in (("steps", 0), ("batch_size", 0), ("holdout_episodes", -1), ("learning_rate", 0.0)):
        with pytest.raises(ValueError, match=field):
            TrainPolicyConfig(data="d", out="o", **{field: value})


def test_zero_evaluation_episodes_train_without_evaluating(reach_data, tmp_path):
    config = policy_config("mp1", reach_data, tmp_path)
    _, history = train_policy(dataclasses.replace(config, eval_episodes=0))
    assert history == [] and load_checkpoint(tmp_path / CHECKPOINT_NAME, "policy")["step"] == 3


def test_training_resumes_from_its_checkpoint(reach_data, tmp_path):
    started = time.perf_counter()
    train_policy(policy_config("mp1", reach_data, tmp_path, steps=2))
    first_call = time.perf_counter() - started
    payload = load_checkpoint(tmp_path / CHECKPOINT_NAME, "policy")
    assert 0 < payload["wall_seconds"] <= first_call
    earlier = 1000.0  # as if the first call had run that long: the resumed run must add to it
    save_checkpoint(tmp_path / CHECKPOINT_NAME, "policy", {**payload, "wall_seconds": earlier})
    first, _ = load_policy(tmp_path / CHECKPOINT_NAME)
    started = time.perf_counter()
    _, history = train_policy(policy_config("mp1", reach_data, tmp_path, steps=4))
    second_call = time.perf_counter() - started
    assert load_checkpoint(tmp_path / CHECKPOINT_NAME, "policy")["step"] == 4
    assert earlier < load_checkpoint(tmp_path / CHECKPOINT_NAME, "policy")["wall_seconds"] <= earlier + second_call
    metrics = load_checkpoint(tmp_path / CHECKPOINT_NAME, "policy")["metrics"]
    assert [row["step"] for row in metrics] == [1, 2, 3, 4]  # 2 before + 2 after resuming
    resumed, _ = load_policy(tmp_path / CHECKPOINT_NAME)
    assert not torch.equal(first.net.input.weight, resumed.net.input.weight)


def test_a_checkpoint_written_before_a_policy_setting_existed_resumes(reach_data, tmp_path):
    """Settings added later (here the stacked horizons and the encoder's count of imagined
    clouds) are absent from an older checkpoint; at their defaults they do what older code
    did, so the run resumes. A setting that differs from the checkpoint's is still refused."""
    train_policy(policy_config("mp1", reach_data, tmp_path, steps=2))
    payload = load_checkpoint(tmp_path / CHECKPOINT_NAME, "policy")
    older = copy.deepcopy(payload["policy_config"])
    del older["stacked_horizons"], older["encoder"]["imagined_clouds"]
    save_checkpoint(tmp_path / CHECKPOINT_NAME, "policy", {**payload, "policy_config": older})
    train_policy(policy_config("mp1", reach_data, tmp_path, steps=4))
    assert load_checkpoint(tmp_path / CHECKPOINT_NAME, "policy")["step"] == 4
    wider = copy.deepcopy(older)
    wider["encoder"]["embed_dim"] += 1
    save_checkpoint(tmp_path / CHECKPOINT_NAME, "policy", {**payload, "policy_config": wider})
    with pytest.raises(CheckpointError, match="embed_dim"):
        train_policy(policy_config("mp1", reach_data, tmp_path, steps=6))
    newer = copy.deepcopy(older)
    newer["encoder"]["a_setting_from_later_code"] = 1
    save_checkpoint(tmp_path / CHECKPOINT_NAME, "policy", {**payload, "policy_config": newer})
    with pytest.raises(CheckpointError, match="cannot read"):
        train_policy(policy_config("mp1", reach_data, tmp_path, steps=6))


def test_a_checkpoint_acts_with_other_actions_per_plan_draws_and_sample_steps(reach_data, tmp_path):
    train_policy(dataclasses.replace(policy_config("mp1", reach_data, tmp_path, steps=1), eval_episodes=0))
    stored, _ = load_policy(tmp_path)
    replanning, _ = load_policy(tmp_path, acting=Acting(n_action_steps=1))
    assert (stored.config.executed_actions, replanning.config.executed_actions) == (3, 1)
    assert all(torch.equal(a, b) for a, b in zip(stored.state_dict().values(), replanning.state_dict().values(),
                                                strict=True))  # the same network and normalizers
    worker = load_torchrl_policy(tmp_path / CHECKPOINT_NAME, Acting(n_action_steps=1, action_draws=3)).policy
    assert (worker.config.executed_actions, worker.action_draws, stored.action_draws) == (1, 3, 1)  # eval workers
    stepped, _ = load_policy(tmp_path, acting=Acting(sample_steps=4))
    window = {key: torch.zeros(1, 2, *shape) for key, shape in (("point_cloud", (8, 3)), ("agent_pos", (4,)))}
    for policy, evaluations in ((stored, 1), (stepped, 4)):  # one per chunk as trained, four when asked
        calls: list[int] = []
        hook = policy.net.register_forward_hook(lambda *_, calls=calls: calls.append(1))
        policy.sample_normalized(window)
        hook.remove()
        assert len(calls) == evaluations
    journal = tmp_path / "journal.jsonl"
    result = evaluate_checkpoint(tmp_path, "reach", 1, seed=0, acting=Acting(n_action_steps=1, action_draws=2),
                                 progress=False, journal=journal)
    assert len(result.successes) == 1
    header, episode = journal.read_text().splitlines()
    journal.write_text(f"{header}\n{json.dumps(json.loads(episode) | {'reward': -1.0})}\n")  # marked
    again = evaluate_checkpoint(tmp_path, "reach", 1, seed=0, acting=Acting(n_action_steps=1, action_draws=2),
                                progress=False, journal=journal)
    assert again.returns == [-1.0]  # read from the journal, not played again
    other = evaluate_checkpoint(tmp_path, "reach", 1, seed=0, acting=Acting(n_action_steps=1), progress=False,
                                journal=journal)
    assert other.returns != [-1.0] and journal.read_text().splitlines()[0] != header  # other acting: replayed


def test_collect_policy_appends_the_policys_own_rollouts_to_its_demonstrations(reach_data, tmp_path):
    """``d2a collect --policy``: in the env settings the policy trained with, so its rollouts join
    that data set, where they are rollouts (no policy trains on them); other env options refused."""
    from d2a.cli import main

    train_policy(dataclasses.replace(policy_config("mp1", reach_data, tmp_path / "run", steps=1), eval_episodes=0))
    data = tmp_path / "data"
    shutil.copytree(reach_data, data)
    main(["collect", "--task", "reach", "--policy", str(tmp_path / "run"), "--episodes", "1", "--seed", "500",
          "--append", "--out", str(data)])
    dataset = DemoDataset.open(data)
    record = dataset.metadata.collections[-1]
    assert record.student == str((tmp_path / "run" / CHECKPOINT_NAME).resolve()) and not record.student_labels
    assert dataset.rollout_episodes() == [2] and len(dataset.demonstrations().metadata.episodes) == 2
    with pytest.raises(SystemExit, match="drop the env options"):
        main(["collect", "--task", "reach", "--policy", str(tmp_path / "run"), "--num-points", "64",
              "--out", str(tmp_path / "other")])


def test_a_diffusion_checkpoint_refuses_more_sample_steps_than_its_schedule_on_loading(reach_data, tmp_path):
    train_policy(dataclasses.replace(policy_config("dp3", reach_data, tmp_path, steps=1), eval_episodes=0))
    assert load_policy(tmp_path, acting=Acting(sample_steps=100))[0].sample_steps == 100  # its 100 timesteps
    with pytest.raises(ValueError, match=r"steps must lie in \[1, 100\], got 101"):
        evaluate_checkpoint(tmp_path, "reach", 1, seed=0, acting=Acting(sample_steps=101), progress=False)


class Killed(Exception):
    """Stands for the process being killed."""


def kill_in_the_second_evaluation(monkeypatch) -> list[int]:
    """Make the trainer's second periodic evaluation raise ``Killed`` (every other one runs);
    returns the first env seed of every evaluation it is asked for, in order."""
    import d2a_agents.policy.train as trainer

    real_evaluation, seeds = trainer.evaluate_checkpoint, []

    def evaluation(*args, seed, **kwargs):
        seeds.append(seed)
        if len(seeds) == 2:
            raise Killed
        return real_evaluation(*args, seed=seed, **kwargs)

    monkeypatch.setattr(trainer, "evaluate_checkpoint", evaluation)
    return seeds


def test_an_evaluation_cut_short_is_run_when_the_training_resumes(reach_data, tmp_path, monkeypatch):
    """Killed during a periodic evaluation (the checkpoint already at that step), the resumed
    run evaluates that step first: its history is the uninterrupted run's."""
    config = dataclasses.replace(policy_config("mp1", reach_data, tmp_path / "cut", steps=4), eval_every=1)
    kill_in_the_second_evaluation(monkeypatch)
    with pytest.raises(Killed):
        train_policy(config)
    interrupted = load_checkpoint(tmp_path / "cut" / CHECKPOINT_NAME, "policy")
    assert interrupted["step"] == 2 and [point["step"] for point in interrupted["history"]] == [1]
    _, resumed = train_policy(config)
    _, straight = train_policy(dataclasses.replace(config, out=str(tmp_path / "straight")))
    assert [point.step for point in resumed] == [1, 2, 3, 4]
    assert resumed == straight


def test_a_periodic_evaluation_killed_part_way_plays_only_its_missing_episodes(reach_data, tmp_path, monkeypatch):
    """Killed after the first of a periodic evaluation's two episodes, the resumed run plays the
    second alone (the first is kept in the run's journal) and ends with the uninterrupted history."""
    from collectors.episode_journal import EpisodeJournal
    from d2a_agents.policy.train import PERIODIC_JOURNAL

    config = dataclasses.replace(policy_config("mp1", reach_data, tmp_path / "cut", steps=4), eval_every=2,
                                 eval_episodes=2)
    real_record, played, killing = EpisodeJournal.record, [], [True]

    def record(journal, seed, episode, seconds):
        real_record(journal, seed, episode, seconds)
        played.append(seed)
        if killing and len(played) == 3:  # the first episode of the step-4 evaluation is on disk
            killing.clear()
            raise Killed

    monkeypatch.setattr(EpisodeJournal, "record", record)
    with pytest.raises(Killed):
        train_policy(config)
    assert played == [10_000, 10_001, 10_000]
    journal = tmp_path / "cut" / PERIODIC_JOURNAL.format(task="reach")
    assert [json.loads(line)["seed"] for line in journal.read_text().splitlines()[1:]] == [10_000]
    played.clear()
    _, resumed = train_policy(config)
    assert played == [10_001]  # the killed evaluation's missing episode, nothing else
    _, straight = train_policy(dataclasses.replace(config, out=str(tmp_path / "straight")))
    assert [point.step for point in resumed] == [2, 4] and resumed == straight


@pytest.mark.parametrize("layouts, seeds", [("fixed", [10_000] * 4), ("fresh", [10_000, 10_001, 10_001, 10_002])])
def test_periodic_evaluations_play_fixed_or_fresh_layouts_across_a_resume(layouts, seeds, reach_data, tmp_path,
                                                                           monkeypatch):
    """"fixed": every evaluation starts at env seed 10000; "fresh": evaluation k plays the k-th
    block of eval_episodes seeds, and a resumed run reuses the block of the evaluation it lost."""
    config = dataclasses.replace(policy_config("mp1", reach_data, tmp_path, steps=3), eval_every=1,
                                 eval_layouts=layouts)
    seen = kill_in_the_second_evaluation(monkeypatch)
    with pytest.raises(Killed):
        train_policy(config)
    _, history = train_policy(config)
    assert seen == seeds and [point.step for point in history] == [1, 2, 3]


def test_imagination_variants_need_a_fitting_world_model(reach_data, tmp_path):
    with pytest.raises(ValueError, match="--world-model"):
        train_policy(policy_config("d2a", reach_data, tmp_path))
    with pytest.raises(CheckpointError, match="no checkpoint"):
        train_policy(policy_config("d2a", reach_data, tmp_path, world_model=str(tmp_path / "missing.pt")))
    train_policy(policy_config("mp1", reach_data, tmp_path / "run", steps=1))
    with pytest.raises(CheckpointError, match="another policy_config"):
        train_policy(policy_config("dp3", reach_data, tmp_path / "run", steps=2))
    other_lr = dataclasses.replace(policy_config("mp1", reach_data, tmp_path / "run", steps=2), learning_rate=0.5)
    with pytest.raises(CheckpointError, match="another run_config.*learning_rate: 0.001 -> 0.5"):
        train_policy(other_lr)  # resuming with another learning rate would mix two runs


def test_a_checkpoint_with_an_unreadable_policy_config_is_refused(reach_data, tmp_path):
    train_policy(policy_config("mp1", reach_data, tmp_path, steps=1))
    payload = load_checkpoint(tmp_path / CHECKPOINT_NAME, "policy")
    del payload["policy_config"]["cfg_thresholds"]  # as written before that field existed
    torch.save(payload, tmp_path / "old.pt")
    with pytest.raises(CheckpointError, match="cannot read.*cfg_thresholds"):
        load_policy(tmp_path / "old.pt")


def test_frames_after_success_are_trimmed_per_episode():
    from tensordict import TensorDict

    from d2a_agents.policy.train import frames_up_to_success

    success = torch.tensor([0, 0, 1, 1, 1, 0, 0, 0, 0, 1, 1], dtype=torch.bool)  # episodes of 5, 3 and 3 steps
    frames = TensorDict({"success": success, "episode": torch.tensor([0] * 5 + [1] * 3 + [2] * 3)}, batch_size=[11])
    keep = frames_up_to_success(frames, keep_after=1)
    # episode 0 succeeds at its step 2: keep steps 0-3; episode 1 never succeeds: keep all;
    # episode 2 succeeds at its step 1: keep steps 0-2 (all of it).
    assert keep.tolist() == [True] * 4 + [False] + [True] * 3 + [True] * 3
    assert frames_up_to_success(frames, keep_after=0).tolist() == [True] * 3 + [False] * 2 + [True] * 3 + [True] * 2 \
        + [False]


def test_world_model_resume_refuses_other_training_settings(reach_data, world_model):
    config = TrainWorldModelConfig(data=reach_data, out=world_model, model=WorldModelConfig(resolution=(16, 16, 8)),
                                   steps=2, batch_size=2, queries=256, validate_every=2, validation_stride=20,
                                   learning_rate=0.5, progress=False)
    before = load_checkpoint(world_model, "world_model")["step"]
    with pytest.raises(CheckpointError, match="another run_config.*learning_rate: 0.001 -> 0.5"):
        train_world_model(config)
    assert load_checkpoint(world_model, "world_model")["step"] == before


def test_a_world_model_checkpoint_written_before_a_setting_existed_resumes(reach_data, world_model, tmp_path):
    """An older world-model config lacks the settings added since: the run resumes where
    their defaults do what older code did (``encoder``), and is refused where they do not
    (without ``plane_pooling`` the model pooled by the mean, not today's max) or where the
    checkpoint holds a setting this code does not know."""
    out = tmp_path / "wm.pt"
    payload = load_checkpoint(world_model, "world_model")
    config = TrainWorldModelConfig(data=reach_data, out=str(out), model=WorldModelConfig(resolution=(16, 16, 8)),
                                   steps=3, batch_size=2, queries=256, validate_every=2, validation_stride=20,
                                   progress=False)

    def store(without: str = "", **extra: object) -> None:
        older = {key: value for key, value in payload["config"].items() if key != without}
        save_checkpoint(out, "world_model", {**payload, "config": {**older, **extra}})

    store(without="encoder")
    train_world_model(config)
    assert load_checkpoint(out, "world_model")["step"] == 3
    store(without="plane_pooling")
    with pytest.raises(CheckpointError, match="plane_pooling: 'mean' -> 'max'"):
        train_world_model(dataclasses.replace(config, steps=4))
    store(a_setting_from_later_code=1)
    with pytest.raises(CheckpointError, match="cannot read"):
        train_world_model(dataclasses.replace(config, steps=4))


def test_bad_world_model_settings_are_refused():
    bad = (("steps", 0), ("batch_size", -1), ("queries", 0), ("validate_every", 0), ("learning_rate", 0.0))
    for field, value in bad:
        with pytest.raises(ValueError, match=field):
            TrainWorldModelConfig(data="d", out="o.pt", **{field: value})


def test_a_multi_task_run_evaluates_every_task(tmp_path):
    from collectors.collect import CollectConfig, collect
    from tests.conftest import SMALL_ENV_KWARGS

    data = tmp_path / "two"
    collect(CollectConfig(tasks=("reach", "button-press"), out=str(data), episodes=1, env_kwargs=SMALL_ENV_KWARGS,
                          progress=False))
    _, history = train_policy(policy_config("mp1", str(data), tmp_path / "run"))
    assert sorted((point.step, point.task) for point in history) == [(3, "button-press"), (3, "reach")]


def test_shifted_windows_move_clouds_and_end_effector_together():
    """Against a hand computation: per window one offset in the table plane, the same for every
    point and step of both clouds and for agent_pos's xyz; heights, the gripper opening and the
    colour channels untouched."""
    from d2a_agents.policy.train import shift_windows

    torch.manual_seed(0)
    observation = {"point_cloud": torch.randn(5, 2, 7, 6), "imagined_point_cloud": torch.randn(5, 2, 7, 3),
                   "agent_pos": torch.randn(5, 2, 4)}
    original = {key: value.clone() for key, value in observation.items()}
    shifted = shift_windows(observation, 0.02, torch.Generator().manual_seed(3))
    offset = shifted["agent_pos"][:, 0, :3] - observation["agent_pos"][:, 0, :3]  # (5, 3)
    assert (offset[:, :2].abs() <= 0.02).all() and offset.abs().max() > 0.005
    assert len(set(offset[:, 0].tolist())) == len(set(offset[:, 1].tolist())) == 5 and (offset[:, 2] == 0).all()
    expected_cloud = observation["point_cloud"].clone()
    for window in range(5):
        expected_cloud[window, :, :, :3] += offset[window]
    torch.testing.assert_close(shifted["point_cloud"], expected_cloud)
    torch.testing.assert_close(shifted["imagined_point_cloud"],
                               observation["imagined_point_cloud"] + offset[:, None, None, :])
    torch.testing.assert_close(shifted["agent_pos"][:, 1, :3], observation["agent_pos"][:, 1, :3] + offset)
    torch.testing.assert_close(shifted["agent_pos"][..., 3], observation["agent_pos"][..., 3])
    assert all(torch.equal(observation[key], original[key]) for key in original)  # the input is left as it was


def test_shift_augmentation_trains_on_meta_world_and_is_refused_where_it_is_not_action_safe(reach_data, tmp_path):
    from d2a_agents.policy.train import DEFAULT_AUGMENT_SHIFT, augment_shift_for

    config = dataclasses.replace(policy_config("mp1", reach_data, tmp_path, steps=2), eval_episodes=0)
    assert config.augment_shift is None  # the cpu preset's: 2 cm where action-safe
    train_policy(config)
    assert load_checkpoint(tmp_path / CHECKPOINT_NAME, "policy")["augment_shift"] == DEFAULT_AUGMENT_SHIFT == 0.02
    state = policy_config("mp1-state", reach_data, tmp_path)
    assert augment_shift_for(config, ["reach"]) == 0.02
    assert augment_shift_for(config, ["adroit-door"]) == augment_shift_for(state, ["reach"]) == 0.0
    explicit = dataclasses.replace(config, augment_shift=0.05)
    assert augment_shift_for(explicit, ["reach"]) == 0.05
    with pytest.raises(ValueError, match="adroit-door"):
        augment_shift_for(explicit, ["reach", "adroit-door"])
    with pytest.raises(ValueError, match="simulator state"):
        augment_shift_for(dataclasses.replace(state, augment_shift=0.05), ["reach"])
    assert augment_shift_for(dataclasses.replace(explicit, augment_shift=0.0), ["adroit-door"]) == 0.0
    with pytest.raises(ValueError, match="augment_shift"):
        dataclasses.replace(config, augment_shift=-0.01)
    paper = TrainPolicyConfig.from_preset(POLICY_PRESETS["paper"], data=reach_data, out=str(tmp_path))
    assert augment_shift_for(paper, ["reach"]) == 0.0  # the paper's recipe moves nothing


def test_a_policy_on_the_first_demonstration_fits_its_normalizers_to_it_alone(reach_data, tmp_path):
    config = dataclasses.replace(policy_config("mp1", reach_data, tmp_path / "one"), demos=1, trim_after_success=-1,
                                 eval_episodes=0)
    policy, _ = train_policy(config)
    dataset = DemoDataset.open(reach_data)
    first, both = dataset.episode(0)["action"], dataset.frames()["action"]
    low = policy.normalizers["action"].low.float()
    assert torch.allclose(low, first.min(0).values) and not torch.allclose(low, both.min(0).values)
    assert torch.allclose(policy.normalizers["action"].high.float(), first.max(0).values)
    assert load_checkpoint(tmp_path / "one" / CHECKPOINT_NAME, "policy")["run_config"]["demos"] == 1
    # Asking for every episode by its count is a run on the whole set, recorded as before the option existed.
    train_policy(dataclasses.replace(config, out=str(tmp_path / "all"), demos=2, steps=1))
    assert load_checkpoint(tmp_path / "all" / CHECKPOINT_NAME, "policy")["run_config"]["demos"] is None
    with pytest.raises(DatasetError, match="fewer than 3 episodes"):
        train_policy(dataclasses.replace(config, out=str(tmp_path / "three"), demos=3))


def test_bench_change_measures_every_cloud_on_held_out_transitions(reach_data, world_model, capsys):
    from benchmarks.change import ChangeBenchConfig, held_out_episodes, run

    dataset = DemoDataset.open(reach_data)
    assert held_out_episodes(dataset, 1) == [1] and held_out_episodes(dataset, None) == [1]
    with pytest.raises(ValueError, match="no episode after the first 2"):
        held_out_episodes(dataset, 2)
    result = run(ChangeBenchConfig(world_model=world_model, data=reach_data, demos=1, stride=3, num_points=16))
    assert set(result) == {"imagined change", "imagined change, likeliest", "observed change", "present",
                           "true change"}
    assert result["true change"]["precision"] == 0.0  # its points are the truth's own
    assert len({row["transitions"] for row in result.values()}) == 1 and result["present"]["transitions"] > 0
    assert all(0 <= row[key] < 1.0 for row in result.values() for key in ("precision", "coverage"))
    assert "| imagined change |" in capsys.readouterr().out


def test_bench_wm_fit_measures_the_trained_and_the_unseen_episodes_apart(reach_data, world_model, capsys):
    """Its persistence figures against a hand computation on each split's own transitions."""
    from scipy.spatial import cKDTree

    from benchmarks.world_model_fit import WorldModelFitConfig, run
    from d2a_agents.world_model.imagine import Imaginer

    rows = run(WorldModelFitConfig(world_model=world_model, data=reach_data, demos=1, stride=40))
    imaginer = Imaginer.from_checkpoint(world_model)
    frames = DemoDataset.open(reach_data).frames()
    episode = np.asarray(frames["episode"]).reshape(-1)
    for name, index in (("trained on", 0), ("unseen", 1)):
        rows_of_episode = np.flatnonzero(episode == index)
        positions = range(0, len(rows_of_episode), 40)
        counts, chamfer = np.zeros(3), 0.0
        for position in positions:
            target = rows_of_episode[min(position + imaginer.config.horizon, len(rows_of_episode) - 1)]
            cloud = np.asarray(frames["point_cloud"][rows_of_episode[position]])[:, :3]
            future = np.asarray(frames["point_cloud"][target])[:, :3]
            now, then = (imaginer.grid.voxelize(torch.as_tensor(c)).numpy() for c in (cloud, future))
            counts += [(now & then).sum(), (now & ~then).sum(), (~now & then).sum()]
            chamfer += cKDTree(future).query(cloud)[0].mean() + cKDTree(cloud).query(future)[0].mean()
        row = rows[name]
        assert (row["episodes"], row["transitions"]) == (1, len(positions))
        assert row["persistence_iou"] == pytest.approx(counts[0] / counts.sum())
        assert row["chamfer_persistence"] == pytest.approx(chamfer / len(positions), rel=1e-4)
        assert 0 <= row["full_iou"] <= 1 and row["chamfer_imagined"] > 0
    assert "| unseen | 1 |" in capsys.readouterr().out
    with pytest.raises(ValueError, match="no episode after the first 2"):
        run(WorldModelFitConfig(world_model=world_model, data=reach_data, demos=2))


def test_bench_policy_fit_measures_the_trained_and_the_unseen_demonstrations_apart(reach_data, world_model, tmp_path,
                                                                                    capsys):
    """Each split's windows: the frames the cpu preset keeps of its episodes (counted by hand),
    less the steps that cannot be current; the second cloud's ratio only where there is one."""
    from benchmarks.policy_fit import PolicyFitConfig, run
    from collectors.dataset import WindowConfig

    runs = {}
    for algo in ("d2a", "mp1"):
        config = policy_config(algo, reach_data, tmp_path / algo, world_model=world_model if algo == "d2a" else None)
        train_policy(dataclasses.replace(config, demos=1, eval_episodes=0))
        runs[algo] = str(tmp_path / algo)
    results = run(PolicyFitConfig(policies=(runs["d2a"], runs["mp1"]), windows=10_000))
    policy = PolicyConfig(algo="d2a", **TINY)
    window = WindowConfig(policy.horizon, policy.n_obs_steps, policy.n_action_steps)
    overrun = max(0, window.horizon - window.n_obs_steps - window.pad_after)
    for algo, expected_second in (("d2a", True), ("mp1", False)):
        for split, episode in (("trained on", 0), ("unseen", 1)):
            check = results[algo][split]
            assert check.windows == frames_kept_by_the_cpu_preset(reach_data, [episode]) - overrun
            assert check.intact > 0 and check.cloud_ratio > 0
            assert (check.imagined_ratio is not None) == expected_second
    assert "| d2a | unseen | 1 |" in capsys.readouterr().out
    with pytest.raises(ValueError, match="no demonstration after the first 2"):
        run(PolicyFitConfig(policies=(runs["mp1"],), demos=2))


def test_bench_policy_fit_can_imagine_from_no_past_actions(reach_data, world_model, tmp_path):
    """Every imagined cloud is the world model's from the recorded histories (some moving) or,
    with ``past_actions="zeros"``, from zeros: imagined here row by row, in the same order
    (the imaginer's sampler is seeded), by a fresh imaginer."""
    from benchmarks.policy_fit import _frames
    from d2a_agents.policy.agent import subsample_cloud
    from d2a_agents.policy.checkpoints import load_policy
    from d2a_agents.world_model.data import WorldModelTransitions
    from d2a_agents.world_model.imagine import Imaginer
    from d2a_envs.wrappers import IMAGINED_KEY

    config = policy_config("d2a", reach_data, tmp_path, world_model=world_model)
    train_policy(dataclasses.replace(config, eval_episodes=0))
    policy, payload = load_policy(tmp_path)
    payload["train_config"]["trim_after_success"] = -1  # rows stay the data set's own
    frames = DemoDataset.open(reach_data).frames()
    count = policy.config.imagined_point_count
    for past_actions in ("recorded", "zeros"):
        imagined = _frames(DemoDataset.open(reach_data), policy, payload, past_actions)[IMAGINED_KEY]
        imaginer = Imaginer.from_checkpoint(world_model, num_points=count)
        table = WorldModelTransitions(frames, imaginer.grid, imaginer.config.horizon, imaginer.config.action_history)
        histories = [table.past_actions(torch.tensor(row)) for row in range(len(table))]
        assert any(history.abs().sum() > 0 for history in histories)  # zeros would change something
        for row, history in enumerate(histories):
            history = history if past_actions == "recorded" else torch.zeros_like(history)
            cloud = imaginer(frames["point_cloud"][table.rows[row]], history)
            assert torch.equal(imagined[row], subsample_cloud(torch.as_tensor(cloud), count))


@pytest.mark.parametrize("algo", ["d2a", "d2a-present", "d2a-oracle"])
def test_the_second_cloud_takes_a_point_count_of_its_own(algo, reach_data, world_model, tmp_path):
    config = policy_config(algo, reach_data, tmp_path, world_model=world_model if algo == "d2a" else None)
    config = dataclasses.replace(config, policy=dataclasses.replace(config.policy, imagined_points=32))
    assert config.policy.imagined_point_count == 32 and config.policy.num_points == 64
    policy, history = train_policy(config)
    assert history[0].episodes == 1  # acting read both clouds at their counts
    payload = load_checkpoint(tmp_path / CHECKPOINT_NAME, "policy")
    if algo == "d2a":
        assert eval_env_kwargs(payload, "reach")["imagined_points"] == 32
    if algo == "d2a-oracle":
        assert eval_env_kwargs(payload, "reach")["expert_future"]["num_points"] == 32
    from d2a_envs.wrappers import IMAGINED_KEY

    observation = {"point_cloud": np.random.default_rng(0).normal(size=(128, 3)).astype(np.float32),
                   "agent_pos": np.zeros(4, np.float32)}
    if algo != "d2a-present":  # the env serves the second cloud
        observation[IMAGINED_KEY] = observation["point_cloud"]
    policy.reset(seed=0)
    policy.select_action(observation)
    frame = policy._history[-1]
    assert frame["point_cloud"].shape == (64, 3) and frame[IMAGINED_KEY].shape == (32, 3)


def test_d2a_present_without_a_count_of_its_own_reads_the_present_cloud_itself(reach_data, tmp_path):
    from d2a_agents.policy.train import training_frames
    from d2a_envs.wrappers import IMAGINED_KEY

    config = policy_config("d2a-present", reach_data, tmp_path).policy
    assert IMAGINED_KEY not in config.observation_keys  # the copy is made from the present cloud when encoding
    own = dataclasses.replace(config, imagined_points=config.num_points)
    frames = training_frames(DemoDataset.open(reach_data), own, None, progress=False)
    assert torch.equal(frames[IMAGINED_KEY], frames["point_cloud"])  # the same count: the same points


def test_the_oracle_reads_the_demonstrations_future_in_training_and_the_simulators_when_acting(reach_data, tmp_path):
    from d2a_agents.policy.agent import ORACLE_HORIZON
    from d2a_agents.policy.train import training_frames
    from d2a_agents.world_model.triplane import WorldModelConfig
    from d2a_envs.wrappers import IMAGINED_KEY

    assert ORACLE_HORIZON == WorldModelConfig().horizon  # the future a world model would imagine, by default
    assert PolicyConfig(algo="d2a-oracle").oracle_horizon == ORACLE_HORIZON
    config = policy_config("d2a-oracle", reach_data, tmp_path)
    horizon = 3  # another horizon than the default, so that the setting is what travels
    config = dataclasses.replace(config, policy=dataclasses.replace(config.policy, oracle_horizon=horizon))
    frames = training_frames(DemoDataset.open(reach_data), config.policy, None, progress=False)
    episode = np.asarray(frames["episode"])
    for row in (0, 5, int(np.flatnonzero(episode == episode[0])[-1])):  # the last row's future is itself
        same_episode = np.flatnonzero(episode == episode[row])
        future = min(row + horizon, int(same_episode[-1]))
        assert torch.equal(frames[IMAGINED_KEY][row], frames["point_cloud"][future])
    _, history = train_policy(config)
    assert history[0].episodes == 1  # it acted on the simulator's look-ahead
    assert_the_steps_it_skips_change_nothing(tmp_path)
    payload = load_checkpoint(tmp_path / CHECKPOINT_NAME, "policy")
    assert payload["world_model"] is None
    assert eval_env_kwargs(payload, "reach")["expert_future"] == {"horizon": horizon, "num_points": 64}
    del payload["policy_config"]["oracle_horizon"]  # a checkpoint written before the setting: the default
    assert eval_env_kwargs(payload, "reach")["expert_future"]["horizon"] == ORACLE_HORIZON


def test_the_stacked_oracle_reads_the_future_at_every_horizon(reach_data, tmp_path):
    from d2a_agents.policy.train import training_frames
    from d2a_envs.wrappers import IMAGINED_KEY

    config = policy_config("d2a-oracle", reach_data, tmp_path)
    config = dataclasses.replace(config, policy=dataclasses.replace(config.policy, oracle_horizon=3,
                                                                     stacked_horizons=(1,)))
    frames = training_frames(DemoDataset.open(reach_data), config.policy, None, progress=False)
    episode = np.asarray(frames["episode"])
    last = int(np.flatnonzero(episode == episode[0])[-1])
    assert frames[IMAGINED_KEY].shape[1:] == (2, 64, 3)
    for row in (0, 5, last - 1):
        for k, horizon in enumerate((1, 3)):
            torch.testing.assert_close(frames[IMAGINED_KEY][row, k], frames["point_cloud"][min(row + horizon, last)])
    _, history = train_policy(config)
    assert history[0].episodes == 1  # it acted on the simulator's stacked look-ahead
    payload = load_checkpoint(tmp_path / CHECKPOINT_NAME, "policy")
    assert eval_env_kwargs(payload, "reach")["expert_future"] == {"horizon": 3, "num_points": 64,
                                                                  "stacked_horizons": [1]}


def test_the_2d_diffusion_policy_trains_on_stored_images_and_acts_on_the_envs(tmp_path):
    from collectors.collect import CollectConfig, collect
    from d2a_agents.policy.train import augment_shift_for
    from tests.conftest import SMALL_ENV_KWARGS

    data = tmp_path / "data"
    collect(CollectConfig(tasks=("reach",), out=str(data), episodes=1, env_kwargs={**SMALL_ENV_KWARGS,
                          "rgb_image_size": 40}, progress=False))
    tiny = dict(encoder=EncoderConfig(image_widths=(4, 4, 8, 8)), network=VelocityNetConfig(hidden=32, layers=2))
    config = TrainPolicyConfig(data=str(data), out=str(tmp_path / "run"), policy=PolicyConfig(algo="dp", **tiny),
                               steps=2, batch_size=4, eval_episodes=1, progress=False)
    assert augment_shift_for(config, ["reach"]) == 0.0  # moving agent_pos without the pixels is not action-safe
    with pytest.raises(ValueError, match="no cloud"):
        augment_shift_for(dataclasses.replace(config, augment_shift=0.02), ["reach"])
    _, history = train_policy(config)
    assert history[-1].episodes == 1
    payload = load_checkpoint(tmp_path / "run" / CHECKPOINT_NAME, "policy")
    assert eval_env_kwargs(payload, "reach")["rgb_image_size"] == 40  # it acts on the images it trained on
    assert payload["reliance"][-1]["perceives"] == "images"
    plain = tmp_path / "plain-data"  # the same demonstration without images
    collect(CollectConfig(tasks=("reach",), out=str(plain), episodes=1, env_kwargs=SMALL_ENV_KWARGS, progress=False))
    with pytest.raises(ValueError, match="--rgb-image-size"):
        train_policy(dataclasses.replace(config, data=str(plain), out=str(tmp_path / "plain")))
    cpu = POLICY_PRESETS["cpu"]
    runs = {algo: TrainPolicyConfig.from_preset(cpu, data="d", out="o",
                                                policy=dataclasses.replace(cpu.policy, algo=algo))
            for algo in ("dp", "mp1")}
    assert (runs["dp"].batch_size, runs["mp1"].batch_size) == (cpu.image_batch_size, cpu.batch_size) == (64, 256)
    assert (runs["dp"].learning_rate, runs["mp1"].learning_rate) == (1e-4, 1e-3)  # Diffusion Policy's own for images


def test_a_checkpoint_is_evaluated_with_its_demonstrations_episode_length_and_held_actions(tmp_path):
    from collectors.collect import CollectConfig, collect
    from tests.conftest import SMALL_ENV_KWARGS

    data = tmp_path / "data"
    collect(CollectConfig(tasks=("reach",), out=str(data), episodes=1, max_episode_steps=70,
                          env_kwargs={**SMALL_ENV_KWARGS, "action_repeat": 2}, progress=False))
    config = policy_config("mp1", str(data), tmp_path / "run", steps=1)
    train_policy(dataclasses.replace(config, eval_episodes=0))
    payload = load_checkpoint(tmp_path / "run" / CHECKPOINT_NAME, "policy")
    assert eval_env_kwargs(payload, "reach")["action_repeat"] == 2
    result = evaluate_checkpoint(tmp_path / "run", "reach", 1, seed=7, progress=False)
    assert result.lengths == [70]  # the demonstrations' episodes, not the default 200


def test_a_data_set_of_rollouts_only_is_refused_for_policy_training(tmp_path):
    from collectors.collect import CollectConfig, collect
    from tests.conftest import SMALL_ENV_KWARGS

    collect(CollectConfig(tasks=("reach",), out=str(tmp_path / "data"), episodes=1, max_episode_steps=8,
                          keep_failures=True, env_kwargs=SMALL_ENV_KWARGS, progress=False))
    with pytest.raises(ValueError, match="no demonstration of reach"):
        train_policy(policy_config("mp1", str(tmp_path / "data"), tmp_path / "run", steps=1))
