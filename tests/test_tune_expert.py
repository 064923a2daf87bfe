"""`d2a bench tune-expert`: the hill climb keeps only improvements, and a tiny real search runs."""

from __future__ import annotations

import json

import pytest

import benchmarks.tune_expert as tune
from benchmarks.tune_expert import TuneConfig
from collectors.adroit_controllers import DoorControllerConfig


def test_the_climb_keeps_a_candidate_only_when_it_scores_better(tmp_path, monkeypatch):
    """A made-up score: one more success per 0.1 rad of turn_step above 0.5, steps fall with push_step."""

    def outcomes(task, settings, seeds, max_steps, noise=0.0):
        wins = min(len(seeds), int((settings.turn_step - 0.5) / 0.1))
        return [int(150 - 50 * settings.push_step)] * wins + [None] * (len(seeds) - wins)

    monkeypatch.setattr(tune, "first_successes", outcomes)
    out = tmp_path / "accepted.json"
    best = tune.run(TuneConfig(iterations=40, episodes=8, step=0.3, out=str(out)))
    accepted = json.loads(out.read_text())
    scores = [(row["successes"], -row["mean_step"]) for row in accepted]
    assert scores == sorted(scores) and len(set(scores)) == len(scores)  # each kept one strictly better
    assert scores[-1] == tune._score(outcomes("door", best, range(8), 200), 200)  # the returned best is the last kept
    assert scores[-1] > scores[0]


def test_a_tiny_real_search_runs_the_controller_on_the_simulator(capsys):
    tune.run(TuneConfig(task="adroit-door", iterations=1, episodes=1, first_seed=1000))
    printed = capsys.readouterr().out
    assert "1/1 tuning episodes solved" in printed and "DoorControllerConfig(" in printed


def test_tuning_noise_is_drawn_from_the_layout_so_every_candidate_meets_the_same_draws():
    """Door's controller on layouts 1000-1001: steps 134 / 138 without noise; a little noise
    delays the first successes the same way on every call; much noise makes it drop the lever."""
    clean = tune.first_successes("door", DoorControllerConfig(), range(1000, 1002), 200)
    noisy = [tune.first_successes("door", DoorControllerConfig(), range(1000, 1002), 200, noise=0.01) for _ in range(2)]
    assert None not in clean and None not in noisy[0]
    assert noisy[0] == noisy[1] and noisy[0] != clean
    assert tune.first_successes("door", DoorControllerConfig(), range(1000, 1002), 200, noise=0.3) == [None, None]


def test_a_task_without_controller_settings_is_refused():
    with pytest.raises(ValueError, match="no controller settings to tune"):
        TuneConfig(task="adroit-pen")
    with pytest.raises(ValueError, match="noise >= 0"):
        TuneConfig(noise=-0.1)
