"""evaluate(): the scripted expert succeeds, a do-nothing policy does not, results repeat and do
not depend on the worker count; the two reporting protocols against hand computations."""

from __future__ import annotations

import functools
import json

import pytest
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from collectors.episode_journal import EpisodeJournal
from collectors.evaluation import EvaluationResult, evaluate, honest_protocol, paper_protocol, wilson_interval
from collectors.experts import ScriptedExpert

TASK = "reach"
ENV_KWARGS = {"image_size": 48, "num_points": 128}


class ZeroPolicy(TensorDictModuleBase):
    """Never moves."""

    def __init__(self) -> None:
        super().__init__()
        self.in_keys, self.out_keys = ["observation"], ["action"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        return tensordict.set("action", torch.zeros(*tensordict.batch_size, 4))


class CountingPolicy(ZeroPolicy):
    """Keeps a step counter that it clears when ``is_init`` marks a new episode."""

    built: list[CountingPolicy] = []

    def __init__(self) -> None:
        super().__init__()
        self.in_keys = ["observation", "is_init"]
        self.steps, self.episode_lengths = 0, []
        CountingPolicy.built.append(self)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if bool(tensordict.get("is_init").all()):
            if self.steps:
                self.episode_lengths.append(self.steps)
            self.steps = 0
        self.steps += 1
        return super().forward(tensordict)


@pytest.fixture(scope="module")
def expert_result() -> EvaluationResult:
    return evaluate(functools.partial(ScriptedExpert, TASK), TASK, 2, seed=0, env_kwargs=ENV_KWARGS, progress=False)


def test_scripted_expert_succeeds_on_every_episode(expert_result: EvaluationResult) -> None:
    assert expert_result.successes == [True, True]
    assert expert_result.success_rate == 1.0
    assert expert_result.seeds == [0, 1]
    assert expert_result.lengths == [200, 200]
    assert all(step is not None and 1 <= step <= 200 for step in expert_result.success_steps)
    assert expert_result.seconds > 0 and "2/2" in expert_result.summary()


def test_a_policy_that_does_not_move_succeeds_less(expert_result: EvaluationResult) -> None:
    still = evaluate(ZeroPolicy, TASK, 2, seed=0, env_kwargs=ENV_KWARGS, progress=False)
    assert still.success_rate < expert_result.success_rate
    assert sum(still.returns) < sum(expert_result.returns)


def test_the_same_seed_gives_the_same_results(expert_result: EvaluationResult) -> None:
    again = evaluate(functools.partial(ScriptedExpert, TASK), TASK, 2, seed=0, env_kwargs=ENV_KWARGS, progress=False)
    assert again.successes == expert_result.successes
    assert again.returns == expert_result.returns
    assert again.success_steps == expert_result.success_steps


def test_ending_at_success_keeps_the_verdicts_and_shortens_the_episodes(expert_result: EvaluationResult) -> None:
    short = evaluate(functools.partial(ScriptedExpert, TASK), TASK, 2, seed=0, env_kwargs=ENV_KWARGS, progress=False,
                     end_on_success=True)
    assert short.successes == expert_result.successes and short.success_steps == expert_result.success_steps
    assert short.lengths == expert_result.success_steps  # each episode ends at the step it succeeded
    assert all(length < 200 for length in short.lengths) and expert_result.lengths == [200, 200]
    assert short.ended_on_success and "up to success" in short.summary()


def test_two_workers_run_the_requested_episodes_with_the_same_results_as_one() -> None:
    policy = functools.partial(ScriptedExpert, TASK)
    kwargs = dict(env_kwargs=ENV_KWARGS, max_steps=60, progress=False)
    parallel = evaluate(policy, TASK, 3, seed=7, workers=2, **kwargs)
    single = evaluate(policy, TASK, 3, seed=7, workers=1, **kwargs)
    assert parallel.workers == 2 and len(parallel.successes) == len(parallel.returns) == 3
    assert parallel.seeds == single.seeds == [7, 8, 9]
    assert parallel.lengths == [60, 60, 60]
    assert parallel.returns == single.returns and parallel.successes == single.successes


def test_a_stateful_policy_sees_is_init_at_every_episode_start() -> None:
    CountingPolicy.built.clear()
    evaluate(CountingPolicy, TASK, 3, seed=0, env_kwargs=ENV_KWARGS, max_steps=20, progress=False)
    (policy,) = CountingPolicy.built
    # The collector calls the policy once when it is built (on the first reset, to find its
    # outputs); the episodes follow, each starting with is_init. The third ends the collection.
    assert policy.episode_lengths == [1, 20, 20]


def test_a_journal_resumes_an_interrupted_evaluation_with_only_the_missing_episodes(tmp_path) -> None:
    path, key = tmp_path / "journal.jsonl", {"policy": "still", "task": TASK}
    kwargs = dict(env_kwargs=ENV_KWARGS, max_steps=20, progress=False)
    full = evaluate(CountingPolicy, TASK, 4, seed=3, journal=EpisodeJournal(path, key), **kwargs)
    header, *episodes = path.read_text().splitlines()
    assert [json.loads(line)["seed"] for line in episodes] == [3, 4, 5, 6]
    # Stopped while writing the third episode; the first one's reward marked to see where it comes from.
    first = json.loads(episodes[0]) | {"reward": -123.0}
    path.write_text("\n".join([header, json.dumps(first), episodes[1], episodes[2][:15]]))
    CountingPolicy.built.clear()
    resumed = evaluate(CountingPolicy, TASK, 4, seed=3, journal=EpisodeJournal(path, key), **kwargs)
    (policy,) = CountingPolicy.built
    assert policy.episode_lengths == [1, 20]  # the build call and one of two episodes run (see above)
    assert resumed.returns == [-123.0, *full.returns[1:]] and resumed.lengths == full.lengths
    assert resumed.seconds > json.loads(episodes[1])["seconds"]
    assert sorted(EpisodeJournal(path, key).finished) == [3, 4, 5, 6]
    assert EpisodeJournal(path, key | {"policy": "another"}).finished == {}  # another key starts over
    assert path.read_text().splitlines() == [json.dumps({"key": key | {"policy": "another"}}, sort_keys=True)]
    with pytest.raises(ValueError, match="local"):
        evaluate(ZeroPolicy, TASK, 1, seed=0, ray_address="local", journal=EpisodeJournal(path, key))


def test_evaluate_rejects_bad_arguments() -> None:
    with pytest.raises(ValueError, match="episodes"):
        evaluate(ZeroPolicy, TASK, 0, seed=0)
    with pytest.raises(ValueError, match="max_steps"):
        evaluate(ZeroPolicy, TASK, 1, seed=0, env_kwargs={"max_episode_steps": 10})
    with pytest.raises(ValueError, match="unknown task"):
        evaluate(ZeroPolicy, "no-such-task", 1, seed=0)


def test_wilson_interval_matches_a_hand_computation() -> None:
    # 8/10, z = 1.96: centre = (0.8 + z^2/20) / (1 + z^2/10) = 0.71674,
    # half width = z / (1 + z^2/10) * sqrt(0.016 + z^2/400) = 0.22658.
    mean, low, high = honest_protocol([True] * 8 + [False] * 2)
    assert mean == pytest.approx(0.8)
    assert low == pytest.approx(0.49016, abs=1e-3)
    assert high == pytest.approx(0.94332, abs=1e-3)
    # 50/100: centre 0.5, half width = 1.96 / 1.038415 * sqrt(0.0025 + 0.000096) = 0.09617.
    assert wilson_interval(50, 100) == pytest.approx((0.40383, 0.59617), abs=1e-3)


def test_wilson_interval_edge_cases() -> None:
    mean, low, high = honest_protocol([True] * 20)
    assert mean == 1.0 and high == 1.0 and low < 1.0
    assert low == pytest.approx(20 / (20 + 1.959964**2), abs=1e-6)  # n / (n + z^2) when all succeed
    mean, low, high = honest_protocol([False] * 5)
    assert mean == 0.0 and low == 0.0 and 0.0 < high < 1.0
    with pytest.raises(ValueError):
        honest_protocol([])


def test_paper_protocol_averages_the_best_five_evaluations() -> None:
    rates = [0.10, 0.55, 0.90, 0.85, 0.40, 0.95, 0.80, 0.70]
    assert paper_protocol(rates) == pytest.approx((0.95 + 0.90 + 0.85 + 0.80 + 0.70) / 5)
    assert paper_protocol(rates, top_k=1) == pytest.approx(0.95)
    assert paper_protocol([0.5, 0.7]) == pytest.approx(0.6)  # fewer than five: all of them
    with pytest.raises(ValueError):
        paper_protocol([])
    with pytest.raises(ValueError):
        paper_protocol([1.5])
