"""The success benchmark: its table against hand-computed figures, and a tiny resumable run."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch

import benchmarks.success as bench
from benchmarks.cells import Cell
from benchmarks.success import SuccessBenchConfig, format_table
from collectors.collect import CollectConfig, collect
from collectors.storage import DatasetError, DemoDataset
from d2a_agents.checkpoint import load_checkpoint
from d2a_agents.policy.agent import PolicyConfig
from d2a_agents.policy.networks import EncoderConfig, VelocityNetConfig
from d2a_agents.policy.train import POLICY_PRESETS, PolicyPreset


def test_table_pools_seeds_and_quotes_the_paper():
    cells = [
        Cell("push", "mp1", 0, periodic=[0.1, 0.5, 0.3], final_wins=3, final_episodes=20, train_seconds=1.0),
        Cell("push", "mp1", 1, periodic=[0.2, 0.4], final_wins=5, final_episodes=20, train_seconds=1.0),
        Cell("hammer", "mp1", 0, periodic=[1.0], final_wins=20, final_episodes=20, train_seconds=1.0),
    ]
    # Top-5 of three and two evaluations is all of them: (0.9 / 3 + 0.6 / 2) / 2 = 0.3.
    assert cells[0].paper == pytest.approx(0.3) and cells[1].paper == pytest.approx(0.3)
    table = format_table(cells, SuccessBenchConfig(seeds=(0, 1)))
    rows = {line.split(" | ")[0].lstrip("| "): line for line in table.splitlines() if line.startswith("| ")}
    # Honest: 8 wins out of 40 pooled episodes = 20 %; Wilson 95 % interval 10.5-34.8 %.
    assert rows["push"] == "| push | 30 / 20 [10-35] | 74 / 85 |"
    assert rows["hammer"] == "| hammer | 100 / 100 [84-100] | - |"
    # Mean over tasks of the per-task figures: paper (30 + 100) / 2, honest (20 + 100) / 2.
    assert rows["mean"] == "| mean | 65.0 / 60.0 | |"


def test_tiny_run_writes_cells_and_a_rerun_reads_them(tmp_path, monkeypatch):
    evaluations = 2
    env_kwargs = {"image_size": 48, "num_points": 128}
    data = tmp_path / "data" / "reach"
    # A collection cut short after its first demonstration: the bench completes it.
    collect(CollectConfig(tasks=("reach",), out=str(data), episodes=1, env_kwargs=env_kwargs, progress=False))
    policy = PolicyConfig(num_points=64, encoder=EncoderConfig(point_widths=(16, 32)),
                          network=VelocityNetConfig(hidden=32, layers=2))
    config = SuccessBenchConfig(tasks=("reach",), algos=("mp1",), demos=2, workdir=str(tmp_path),
                                policy=PolicyPreset(policy, steps=4, batch_size=4, learning_rate=1e-3),
                                evaluations=evaluations, eval_episodes=1, seeds=(0,), final_episodes=0,
                                env_kwargs=env_kwargs)
    (cell,) = bench.run(config)
    assert len(DemoDataset.open(data).metadata.episodes) == 2
    assert (cell.task, cell.algo, cell.seed) == ("reach", "mp1", 0)
    assert len(cell.periodic) == evaluations and cell.final_episodes == 1
    assert cell.final_wins == round(cell.periodic[-1])  # the last periodic evaluation is the final checkpoint's
    stored = json.loads(bench.cell_path(config, "reach", "mp1", 0).read_text())
    assert stored["periodic"] == cell.periodic
    trained = tmp_path / "runs" / bench._cell_name(config, "reach", "mp1", 0) / "policy.pt"
    payload = load_checkpoint(trained, "policy")
    assert cell.train_seconds == payload["wall_seconds"]  # summed over resumed calls
    assert stored["reliance"] == payload["reliance"][-1] and stored["reliance"]["intact"] > 0  # kept with the cell
    assert (tmp_path / "success.png").stat().st_size > 0
    # A cell on the first demonstration of the pool of two: named apart, trained on episode 0 only.
    (one,) = bench.run(dataclasses.replace(config, demos=1, pool=2))
    assert (one.demos, cell.demos) == (1, 2)
    run = tmp_path / "runs" / bench._cell_name(dataclasses.replace(config, demos=1), "reach", "mp1", 0)
    assert "_e2_d1_" in run.name and len(DemoDataset.open(data).metadata.episodes) == 2
    assert load_checkpoint(run / "policy.pt", "policy")["run_config"]["demos"] == 1
    with pytest.raises(ValueError, match="cannot give cells 2"):
        dataclasses.replace(config, pool=1)

    def no_training(*args, **kwargs):
        raise AssertionError("a finished cell was trained again")

    monkeypatch.setattr(bench, "train_policy", no_training)
    assert bench.run(config) == [cell]
    # A new cell on clouds of another size must not train on these demonstrations.
    other_clouds = dataclasses.replace(config, seeds=(1,), env_kwargs={**env_kwargs, "num_points": 256})
    with pytest.raises(DatasetError, match="collected with env kwargs"):
        bench.run(other_clouds)


def _tiny_bench(tmp_path, **fields) -> SuccessBenchConfig:
    """One reach cell of a 2-step policy on one demonstration, small clouds, one evaluation episode."""
    policy = PolicyConfig(num_points=64, encoder=EncoderConfig(point_widths=(16, 32)),
                          network=VelocityNetConfig(hidden=32, layers=2))
    settings = dict(tasks=("reach",), algos=("mp1",), demos=1, workdir=str(tmp_path),
                    policy=PolicyPreset(policy, steps=2, batch_size=4, learning_rate=1e-3), evaluations=1,
                    eval_episodes=1, seeds=(0,), final_episodes=0, env_kwargs={"image_size": 48, "num_points": 128})
    return SuccessBenchConfig(**{**settings, **fields})


def test_a_cp_cell_trains_its_edm_teacher_first_and_the_edm_cell_finds_it_done(tmp_path):
    config = _tiny_bench(tmp_path, algos=("cp",))
    (cell,) = bench.run(config)
    teacher = tmp_path / "runs" / bench._cell_name(config, "reach", "edm", 0) / "policy.pt"
    student = load_checkpoint(tmp_path / "runs" / bench._cell_name(config, "reach", "cp", 0) / "policy.pt", "policy")
    assert cell.algo == "cp" and student["teacher"] == str(teacher.resolve())
    (edm,) = bench.run(dataclasses.replace(config, algos=("edm",)))
    assert edm.algo == "edm" and load_checkpoint(teacher, "policy")["step"] == 2  # resumed finished: no step more


def test_dart_cells_train_on_their_own_demonstrations(tmp_path):
    config = _tiny_bench(tmp_path, dart_noise=0.05)
    bench.run(config)
    assert DemoDataset.open(tmp_path / "data" / "reach_dart0.05").metadata.collections[0].dart_noise == 0.05
    assert not (tmp_path / "data" / "reach").exists()
    assert bench.cell_path(config, "reach", "mp1", 0).name.startswith("reach_mp1_s0_e1_d1_dart0.05_")


def test_cells_of_another_demo_seed_train_on_another_set_of_demonstrations(tmp_path):
    config = _tiny_bench(tmp_path, demo_seed=1000)
    bench.run(config)
    (collection,) = DemoDataset.open(tmp_path / "data" / "reach_pool1000").metadata.collections
    assert collection.seed == 1000  # its layouts are env seeds 1000 on, not pool 0's 0 on
    assert not (tmp_path / "data" / "reach").exists()
    assert bench.cell_path(config, "reach", "mp1", 0).name.startswith("reach_mp1_s0_e1_d1_pool1000_")


@pytest.mark.parametrize("demo_seed", [5, 9999])
def test_a_demo_seed_whose_layouts_could_meet_another_pools_or_the_evaluations_is_refused(demo_seed):
    # A pool of 20 may take up to 200 attempts: seeds 0-199 are pool 0's, 9800 on reach the evaluations' 10000.
    with pytest.raises(ValueError, match="demo_seed"):
        SuccessBenchConfig(demos=2, pool=20, demo_seed=demo_seed)
    SuccessBenchConfig(demos=2, pool=20, demo_seed=200)


def test_cells_of_a_chosen_adroit_expert_train_on_its_own_demonstrations(tmp_path):
    config = _tiny_bench(tmp_path, tasks=("adroit-pen",), expert="controller")
    bench.run(config)
    assert DemoDataset.open(tmp_path / "data" / "adroit-pen_controller").metadata.collections[0].expert == "controller"
    assert bench.cell_path(config, "adroit-pen", "mp1", 0).name.startswith("adroit-pen_mp1_s0_e1_d1_controller_")
    with pytest.raises(ValueError, match=r"applies to Adroit tasks; \['reach'\]"):
        _tiny_bench(tmp_path, tasks=("adroit-pen", "reach"), expert="planner")
    with pytest.raises(ValueError, match="expert must be one of"):
        _tiny_bench(tmp_path, tasks=("adroit-pen",), expert="oracle")


def test_cells_acting_on_several_draws_evaluate_so_and_are_named_apart(tmp_path, monkeypatch):
    import d2a_agents.policy.train as training

    config = _tiny_bench(tmp_path, action_draws=3, final_episodes=1)
    draws = []

    def recording(evaluate):
        def wrapper(*args, **kwargs):
            draws.append(kwargs["acting"].action_draws)
            return evaluate(*args, **kwargs)
        return wrapper

    monkeypatch.setattr(training, "evaluate_checkpoint", recording(training.evaluate_checkpoint))
    monkeypatch.setattr(bench, "evaluate_checkpoint", recording(bench.evaluate_checkpoint))
    (cell,) = bench.run(config)
    assert draws == [3, 3] and cell.final_episodes == 1  # the periodic evaluation, then the final one
    journal = tmp_path / "runs" / bench._cell_name(config, "reach", "mp1", 0) / bench.FINAL_JOURNAL
    (episode,) = [json.loads(line) for line in journal.read_text().splitlines()[1:]]  # kept for a resumed call
    assert episode["seed"] == config.final_seed and cell.final_seconds >= episode["seconds"] > 0
    assert bench.cell_path(config, "reach", "mp1", 0).name.startswith("reach_mp1_s0_e1_d1_draws3_")
    assert "draws" not in bench._cell_name(dataclasses.replace(config, action_draws=1), "reach", "mp1", 0)
    with pytest.raises(ValueError, match="action_draws must be at least 1"):
        dataclasses.replace(config, action_draws=0)


def test_a_bench_with_an_image_policy_collects_images_and_evaluates_the_others_without(tmp_path):
    from d2a_agents.policy.checkpoints import eval_env_kwargs

    env_kwargs = {"image_size": 48, "num_points": 128}
    policy = PolicyConfig(num_points=64, encoder=EncoderConfig(point_widths=(16, 32), image_widths=(4, 4, 8, 8)),
                          network=VelocityNetConfig(hidden=32, layers=2))
    config = SuccessBenchConfig(tasks=("reach",), algos=("dp", "mp1"), demos=1, workdir=str(tmp_path),
                                policy=PolicyPreset(policy, steps=2, batch_size=4, learning_rate=1e-3),
                                evaluations=1, eval_episodes=1, seeds=(0,), final_episodes=0, env_kwargs=env_kwargs,
                                rgb_image_size=40)
    assert [cell.algo for cell in bench.run(config)] == ["dp", "mp1"]
    data = DemoDataset.open(tmp_path / "data" / "reach_rgb40")
    assert data.episode(0)["image"].shape[1:] == (40, 40, 3)
    runs = {algo: load_checkpoint(tmp_path / "runs" / bench._cell_name(config, "reach", algo, 0) / "policy.pt",
                                  "policy") for algo in ("dp", "mp1")}
    assert eval_env_kwargs(runs["dp"], "reach")["rgb_image_size"] == 40
    assert "rgb_image_size" not in eval_env_kwargs(runs["mp1"], "reach")  # the cloud policy is spared the drawing


@pytest.mark.parametrize(("steps", "evaluations"), [(4000, 5), (4000, 15), (3000, 15), (10, 4), (7, 7), (7, 1)])
def test_evaluation_interval_gives_the_asked_count(steps, evaluations):
    interval = bench.evaluation_interval(steps, evaluations)
    # What train_policy evaluates: every multiple of the interval, and the final step.
    evaluated = {step for step in range(1, steps + 1) if step % interval == 0 or step == steps}
    assert len(evaluated) == evaluations


@pytest.mark.parametrize(("steps", "evaluations"), [(10, 6), (10, 0), (10, 11)])
def test_evaluation_interval_refuses_counts_it_cannot_give(steps, evaluations):
    with pytest.raises(ValueError):
        bench.evaluation_interval(steps, evaluations)


def test_cells_on_fresh_layouts_are_named_apart_from_fixed_ones():
    fixed = SuccessBenchConfig(evaluations=15)
    fresh = dataclasses.replace(fixed, eval_layouts="fresh")
    assert bench._cell_name(fixed, "push", "d2a", 1) == "push_d2a_s1_e15"  # the names of cells stored before
    assert bench._cell_name(fresh, "push", "d2a", 1) == "push_d2a_s1_e15_fresh"


def test_cells_of_another_policy_budget_are_named_apart():
    cpu = SuccessBenchConfig(evaluations=15)
    longer = dataclasses.replace(cpu, policy=dataclasses.replace(POLICY_PRESETS["cpu"], steps=6000))
    paper = dataclasses.replace(cpu, policy=POLICY_PRESETS["paper"])
    names = {bench._cell_name(config, "push", "d2a", 1) for config in (cpu, longer, paper)}
    assert len(names) == 3
    assert bench._cell_name(paper, "push", "d2a", 1) == "push_d2a_s1_e15_paper"
    assert bench._cell_name(longer, "push", "d2a", 1) == "push_d2a_s1_e15_steps6000"  # what differs from cpu
    cpu_policy = POLICY_PRESETS["cpu"].policy
    points = dataclasses.replace(cpu, policy=dataclasses.replace(POLICY_PRESETS["cpu"], policy=dataclasses.replace(
        cpu_policy, num_points=128, oracle_horizon=12)))
    assert bench._cell_name(points, "push", "d2a", 1) == "push_d2a_s1_e15_num_points128_oracle_horizon12"
    wide_policy = dataclasses.replace(cpu_policy, num_points=128, imagined_points=256, oracle_horizon=12)
    wide = dataclasses.replace(cpu, policy=dataclasses.replace(POLICY_PRESETS["cpu"], steps=6000, policy=wide_policy))
    assert bench._cell_name(wide, "push", "d2a", 1).startswith("push_d2a_s1_e15_6000steps-")  # too long to spell
    # The tag depends on the preset's fields only, not on the object.
    again = dataclasses.replace(cpu, policy=dataclasses.replace(POLICY_PRESETS["cpu"], steps=6000))
    assert bench._cell_name(again, "push", "d2a", 1) == bench._cell_name(longer, "push", "d2a", 1)


def test_cells_of_another_demonstration_count_are_named_apart():
    ten = SuccessBenchConfig(evaluations=15, eval_layouts="fresh")
    five = dataclasses.replace(ten, demos=5)
    assert bench._cell_name(ten, "push", "mp1", 0) == "push_mp1_s0_e15_fresh"  # the names of cells stored before
    assert bench._cell_name(five, "push", "mp1", 0) == "push_mp1_s0_e15_fresh_d5"


def test_imagining_cells_of_a_world_model_with_rollouts_are_named_apart():
    plain = SuccessBenchConfig(evaluations=15, eval_layouts="fresh", demos=5)
    rollouts = dataclasses.replace(plain, wm_rollouts=20)
    assert bench._cell_name(rollouts, "push", "d2a", 0) == "push_d2a_s0_e15_fresh_d5_wmr20n0.3"
    assert bench._cell_name(rollouts, "push", "mp1", 0) == bench._cell_name(plain, "push", "mp1", 0)  # no world model
    own = dataclasses.replace(rollouts, wm_policy_rollouts="d2a")
    assert bench._cell_name(own, "push", "d2a", 0) == "push_d2a_s0_e15_fresh_d5_wmr20pd2a"
    other_seed = dataclasses.replace(own, wm_policy_seed=1)
    assert bench._cell_name(other_seed, "push", "d2a", 2) == "push_d2a_s2_e15_fresh_d5_wmr20pd2as1"
    with pytest.raises(ValueError, match="give their count"):
        dataclasses.replace(plain, wm_policy_rollouts="d2a")
    with pytest.raises(ValueError, match="name its algo"):
        dataclasses.replace(rollouts, wm_policy_seed=1)


def test_a_world_model_of_noisy_expert_rollouts_gets_them_beside_the_pool_in_its_data_set(tmp_path):
    config = _tiny_bench(tmp_path, wm_rollouts=1, rollout_noise=0.5)
    data = bench._dataset(config, "reach")
    assert data.name == "reach"  # the noisy expert's rollouts join the pool's own data set
    dataset = DemoDataset.open(data)
    (rollout,) = dataset.rollout_episodes()
    record = dataset.metadata.collections[dataset.metadata.episodes[rollout].collection]
    assert (record.action_noise, record.keep_failures, record.student, record.seed) == (
        0.5, True, None, bench.ROLLOUT_SEED)


def test_a_world_model_of_a_policys_rollouts_gets_the_pool_again_and_that_policys_own_episodes(tmp_path):
    """``wm_policy_rollouts``: a data set apart holding the same demonstrations as the pool
    (collected again from the same seeds) and the rollouts of the bench's seed-0 cell of that
    algo, its own actions stored; refused while that cell is not finished."""
    config = _tiny_bench(tmp_path)
    own = dataclasses.replace(config, wm_rollouts=1, wm_policy_rollouts="mp1")
    with pytest.raises(ValueError, match="finish that cell first"):
        bench._dataset(own, "reach")
    with pytest.raises(ValueError, match="mp1 seed-1 cell"):
        bench._dataset(dataclasses.replace(own, wm_policy_seed=1), "reach")
    bench.run(config)  # the plain mp1 cell of seed 0, on the pool
    data = bench._dataset(own, "reach")
    pool = DemoDataset.open(tmp_path / "data" / "reach")
    again = DemoDataset.open(data)
    assert data.name == "reach_wmr1pmp1" and again.demonstrations().metadata.episodes == pool.metadata.episodes
    assert torch.equal(again.demonstrations().frames()["point_cloud"], pool.frames()["point_cloud"])
    (rollout,) = again.rollout_episodes()
    record = again.metadata.collections[again.metadata.episodes[rollout].collection]
    run = tmp_path / "runs" / bench._cell_name(config, "reach", "mp1", 0) / "policy.pt"
    assert (record.student, record.student_labels, record.seed) == (str(run.resolve()), False, bench.ROLLOUT_SEED)
