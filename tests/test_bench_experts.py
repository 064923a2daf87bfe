"""The learnability check of ``d2a bench experts``: a state policy on the expert's demonstrations."""

from __future__ import annotations

import pytest

from benchmarks.experts import IMITATION_SEED, ExpertBenchConfig, imitation_success
from collectors.storage import DemoDataset
from d2a_agents.checkpoint import load_checkpoint
from d2a_agents.policy.checkpoints import policy_file


@pytest.mark.parametrize("algo", ["mp1-state", "dp3-state"])
def test_imitation_trains_a_state_policy_on_the_demonstrations_and_evaluates_new_layouts(algo, tmp_path):
    config = ExpertBenchConfig(tasks=("reach",), env_kwargs={"image_size": 32, "num_points": 32}, workers=1,
                               imitation_demos=2, imitation_episodes=2, imitation_steps=2, workdir=str(tmp_path),
                               imitation_algo=algo)
    result = imitation_success(config, "reach")
    assert result.episodes == 2 and result.seeds == [IMITATION_SEED, IMITATION_SEED + 1]
    assert len(DemoDataset.open(tmp_path / "data" / "reach").metadata.episodes) == 2
    payload = load_checkpoint(policy_file(tmp_path / "runs" / f"reach_{algo}_d2"), "policy")
    assert payload["policy_config"]["algo"] == algo and payload["step"] == 2
    assert payload["policy_config"]["encoder"]["use_cloud"] is False


@pytest.mark.parametrize("algo", ["mp1", "dp3", "no-such-algo"])
def test_the_check_refuses_a_policy_that_reads_clouds(algo):
    with pytest.raises(ValueError, match="imitation_algo must be a state policy"):
        ExpertBenchConfig(imitation_algo=algo)


def test_the_check_collects_with_dart_noise_apart_when_asked(tmp_path):
    config = ExpertBenchConfig(tasks=("reach",), env_kwargs={"image_size": 32, "num_points": 32}, workers=1,
                               imitation_demos=1, imitation_episodes=1, imitation_steps=2, workdir=str(tmp_path),
                               imitation_dart_noise=0.05)
    imitation_success(config, "reach")
    dataset = DemoDataset.open(tmp_path / "data" / "reach_dart0.05")
    assert dataset.metadata.collections[0].dart_noise == 0.05
    assert (tmp_path / "runs" / "reach_mp1-state_d1_dart0.05" / "policy.pt").exists()


def test_the_check_evaluates_with_the_draws_it_is_given(tmp_path, monkeypatch):
    import benchmarks.experts

    seen = []
    real = benchmarks.experts.evaluate_checkpoint
    monkeypatch.setattr(benchmarks.experts, "evaluate_checkpoint",
                        lambda *args, acting, **kwargs: seen.append(acting) or real(*args, acting=acting, **kwargs))
    config = ExpertBenchConfig(tasks=("reach",), env_kwargs={"image_size": 32, "num_points": 32}, workers=1,
                               imitation_demos=1, imitation_episodes=1, imitation_steps=2, workdir=str(tmp_path),
                               imitation_action_draws=4)
    assert imitation_success(config, "reach").episodes == 1
    assert [acting.action_draws for acting in seen] == [4]


def test_the_check_collects_with_the_adroit_expert_it_is_given_apart(tmp_path):
    config = ExpertBenchConfig(tasks=("adroit-pen", "reach"), env_kwargs={"image_size": 32, "num_points": 32},
                               workers=1, imitation_demos=1, imitation_episodes=1, imitation_steps=2,
                               workdir=str(tmp_path), expert="controller")
    assert config.settings("adroit-pen").kind == "controller"
    assert config.settings("reach").kind is None  # Meta-World: its one scripted expert
    imitation_success(config, "adroit-pen")
    dataset = DemoDataset.open(tmp_path / "data" / "adroit-pen_controller")
    assert dataset.metadata.collections[0].expert == "controller"
    assert (tmp_path / "runs" / "adroit-pen_mp1-state_d1_controller" / "policy.pt").exists()


def test_the_bench_refuses_an_unknown_expert_kind():
    with pytest.raises(ValueError, match="expert must be one of"):
        ExpertBenchConfig(expert="oracle")


def test_failures_are_rerun_alone_with_the_longer_limit(monkeypatch):
    """Reach's expert needs more than 3 steps: both episodes fail at 3 and succeed within 100,
    each rerun once, with its own seed."""
    import benchmarks.experts
    from benchmarks.experts import _env_kwargs, _expert, failure_reason
    from collectors.evaluation import evaluate

    config = ExpertBenchConfig(tasks=("reach",), episodes=2, seed=5, max_steps=3, late_max_steps=100, workers=1,
                               env_kwargs={"image_size": 32, "num_points": 32})
    result = evaluate(_expert(config, "reach"), "reach", 2, 5, _env_kwargs(config, "reach"), max_steps=3,
                      progress=False)
    assert result.successes == [False, False]
    reruns = []
    real = benchmarks.experts.evaluate
    monkeypatch.setattr(benchmarks.experts, "evaluate",
                        lambda *args, **kwargs: reruns.append(args[2:4]) or real(*args, **kwargs))
    reason = failure_reason(result, config)
    assert reruns == [(1, 5), (1, 6)]
    assert reason.startswith("late success within 100 steps (seed 5 at step ") and "seed 6 at step " in reason


def test_one_worker_skips_the_parallel_timing(capsys):
    from benchmarks.experts import run

    rows = run(ExpertBenchConfig(tasks=("reach",), episodes=1, workers=1, progress=False,
                                 env_kwargs={"image_size": 32, "num_points": 32}))
    assert [row["task"] for row in rows] == ["reach"]
    out = capsys.readouterr().out
    assert "| reach |" in out and "Parallel evaluation" not in out
