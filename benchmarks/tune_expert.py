"""Tune an Adroit controller's settings: hill climbing on success, then speed, over seeded episodes.

Each iteration perturbs two settings of the best configuration so far (Gaussian, a fraction
of their range, clipped to it) and keeps the perturbation when it succeeds in more of the
tuning episodes, or in as many but sooner. The episodes run on the bare simulator (no point
clouds) through the expert's own path (the physics vector into a replica, the controller
there), on layouts ``first_seed ..``, apart from the demonstrations' (0 ..) and the
evaluations'. With ``noise``, every tuning episode executes the controller's action plus
Gaussian noise of that std, the draws ``d2a collect --dart-noise`` makes on that layout, so that
every candidate meets the same ones: the search then maximises the noise the controller
tolerates, which bounds the recovery its DART demonstrations can show. Prints the best settings
as the config's constructor call, to paste into :mod:`collectors.adroit_controllers`, and the
time the search took.
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

import d2a_envs
from collectors.adroit_controllers import CONTROLLERS, ControllerReplica
from collectors.experts import step_noise
from d2a_envs.suites.adroit import AdroitEnv

# The range each setting is searched in.
SEARCH_SPACE = {
    "door": {
        "grasp_closure": (0.9, 1.4), "turn_step": (0.5, 1.2), "pull_step": (0.2, 0.9), "pull_roll": (0.6, 1.4),
        "release_at": (0.3, 0.9), "push_step": (0.3, 1.4), "round_x": (-0.75, -0.58), "round_y": (0.06, 0.16),
        "push_x": (-0.5, -0.35), "push_y": (0.06, 0.13), "push_height": (0.12, 0.26), "arm_gain": (1.0, 2.2),
        "round_gain": (0.8, 2.2),
    },
    "hammer": {
        "grasp_x": (-0.1, -0.06), "grasp_y": (-0.03, 0.01), "grasp_z": (-0.015, 0.005), "hover": (0.04, 0.1),
        "grasp_closure": (1.2, 1.6), "lift": (0.08, 0.2), "deviation": (-0.79, -0.5), "extension": (-0.52, 0.0),
        "pitch_gain": (0.5, 3.0), "aim_yaw": (0.15, 0.3), "swing": (0.1, 0.5), "aligned": (0.01, 0.04),
        "arm_gain": (0.8, 1.8),
    },
}


@dataclass(frozen=True)
class TuneConfig:
    """What ``d2a bench tune-expert`` searches.

    Attributes:
        task: an Adroit task with a controller.
        iterations: perturbations tried after the starting point (the current defaults).
        episodes: tuning episodes per candidate (layouts ``first_seed ..``).
        first_seed: seed of the first tuning episode.
        step: perturbation standard deviation as a fraction of each setting's range.
        seed: seed of the perturbations.
        max_steps: episode length (the benchmark's 200).
        noise: std of the Gaussian noise on every executed action (0: the controller's own actions).
        out: JSON file of every accepted candidate (None: not written).
    """

    task: str = "adroit-door"
    iterations: int = 60
    episodes: int = 8
    first_seed: int = 1000
    step: float = 0.15
    seed: int = 0
    max_steps: int = d2a_envs.DEFAULT_MAX_EPISODE_STEPS
    noise: float = 0.0
    out: str | None = None

    def __post_init__(self) -> None:
        task = d2a_envs.get_task(self.task).task
        if task not in SEARCH_SPACE:
            raise ValueError(f"no controller settings to tune for {self.task}: tunable are {sorted(SEARCH_SPACE)}")
        if self.iterations < 0 or self.episodes < 1 or not 0 < self.step <= 1 or not self.noise >= 0:
            raise ValueError("iterations >= 0, episodes >= 1, 0 < step <= 1 and noise >= 0, please")


def first_successes(task: str, settings: object, seeds: range, max_steps: int,
                    noise: float = 0.0) -> list[int | None]:
    """The step of each episode's first success (None: none within ``max_steps``), the executed
    actions perturbed by Gaussian noise of std ``noise`` (:func:`step_noise` of the episode's seed)."""
    env = AdroitEnv(task, state_obs=False, physics_obs=True)
    replica = ControllerReplica(task, settings)
    outcomes: list[int | None] = []
    for seed in seeds:
        observation, _ = env.reset(seed=seed)
        first = None
        for step in range(max_steps):
            action = replica.act(observation["physics"])
            if noise:
                action = np.clip(action + step_noise(seed, step, noise, action.shape), -1.0, 1.0).astype(action.dtype)
            observation, _, _, _, info = env.step(action)
            if info["success"]:
                first = step
                break
        outcomes.append(first)
    env.close()
    return outcomes


def _score(outcomes: list[int | None], max_steps: int) -> tuple[int, float]:
    """(successes, -mean first-success step with failures counted as ``max_steps``): higher is better."""
    steps = [max_steps if step is None else step for step in outcomes]
    return sum(step is not None for step in outcomes), -float(np.mean(steps))


def run(config: TuneConfig) -> object:
    """Search and return the best settings; print them and the search's time."""
    task = d2a_envs.get_task(config.task).task
    _, settings_type = CONTROLLERS[task]
    space = SEARCH_SPACE[task]
    seeds = range(config.first_seed, config.first_seed + config.episodes)
    rng = np.random.default_rng(config.seed)
    start = time.perf_counter()
    best = settings_type()
    best_score = _score(first_successes(task, best, seeds, config.max_steps, config.noise), config.max_steps)
    accepted = [{"iteration": 0, "successes": best_score[0], "mean_step": -best_score[1], **dataclasses.asdict(best)}]
    bar = tqdm(range(1, config.iterations + 1), desc=f"tune {task}")
    for iteration in bar:
        changes = {}
        for name in rng.choice(sorted(space), size=2, replace=False):
            low, high = space[name]
            changes[name] = float(np.clip(getattr(best, name) + rng.normal(0.0, config.step * (high - low)), low, high))
        candidate = dataclasses.replace(best, **changes)
        score = _score(first_successes(task, candidate, seeds, config.max_steps, config.noise), config.max_steps)
        if score > best_score:
            best, best_score = candidate, score
            accepted.append({"iteration": iteration, "successes": score[0], "mean_step": -score[1],
                             **dataclasses.asdict(best)})
        bar.set_postfix(successes=f"{best_score[0]}/{config.episodes}", mean_step=f"{-best_score[1]:.1f}")
    minutes = (time.perf_counter() - start) / 60
    fields = ", ".join(f"{name}={round(value, 3)!r}" for name, value in dataclasses.asdict(best).items())
    under = f" under action noise {config.noise}" if config.noise else ""
    print(f"{task}: {best_score[0]}/{config.episodes} tuning episodes solved{under}, first success at step "
          f"{-best_score[1]:.1f} on average; searched {config.iterations} candidates in {minutes:.1f} min (1 process)")
    print(f"{settings_type.__name__}({fields})")
    if config.out:
        Path(config.out).parent.mkdir(parents=True, exist_ok=True)
        Path(config.out).write_text(json.dumps(accepted, indent=1))
    return best
