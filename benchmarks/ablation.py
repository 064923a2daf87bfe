"""Ablations of the ``cpu`` policy preset (``d2a bench ablate``): one change at a time.

Each run trains ``mp1`` (or another variant) with one named change to the ``cpu`` preset on a
data set, holding out its last episode for the perception check, then evaluates the final
checkpoint on ``episodes`` new layouts (the honest protocol). A run writes
``<workdir>/<task>_<change>_<algo>_s<seed>.json`` and is skipped when that file exists, so a
grid can be run piecewise (two at a time on two cores: one thread each) and tabulated with
``--table``.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from collectors.atomic import atomic_write_text
from collectors.evaluation import honest_protocol
from d2a_agents.checkpoint import load_checkpoint
from d2a_agents.policy.checkpoints import CHECKPOINT_NAME, evaluate_checkpoint
from d2a_agents.policy.train import TrainPolicyConfig, train_policy


def _policy(**changes: object) -> Callable[[TrainPolicyConfig], TrainPolicyConfig]:
    return lambda config: dataclasses.replace(config, policy=dataclasses.replace(config.policy, **changes))


def _encoder(**changes: object) -> Callable[[TrainPolicyConfig], TrainPolicyConfig]:
    def change(config: TrainPolicyConfig) -> TrainPolicyConfig:
        encoder = dataclasses.replace(config.policy.encoder, **changes)
        return dataclasses.replace(config, policy=dataclasses.replace(config.policy, encoder=encoder))

    return change


def _training(**changes: object) -> Callable[[TrainPolicyConfig], TrainPolicyConfig]:
    return lambda config: dataclasses.replace(config, **changes)


def _previous_preset(config: TrainPolicyConfig) -> TrainPolicyConfig:
    """The cpu preset before the perception work: 256 raw-metre points, batch 32, p = 1, no
    LayerNorm after the cloud projection (benchmarks/train.py's reference row)."""
    from benchmarks.train import PREVIOUS_CPU_PRESET

    preset = PREVIOUS_CPU_PRESET
    policy = dataclasses.replace(preset.policy, algo=config.policy.algo, normalize_clouds=False)
    return dataclasses.replace(config, **{**preset.training_fields(), "policy": policy})


# name -> the one change to the cpu preset ("previous-preset": every change at once, undone)
CHANGES: dict[str, Callable[[TrainPolicyConfig], TrainPolicyConfig]] = {
    "none": _training(),
    "raw-clouds": _policy(normalize_clouds=False),
    "adaptive-power-1": _policy(adaptive_power=1.0),
    "adaptive-power-0.5": _policy(adaptive_power=0.5),
    "no-projection-layernorm": _encoder(project_norm=False),
    "point-mlp-float32": _encoder(point_dtype="float32"),
    "points-128": _policy(num_points=128),
    "points-256": _policy(num_points=256),
    "batch-32": _training(batch_size=32),
    "steps-2000": _training(steps=2000),
    "steps-8000": _training(steps=8000),
    "trim-after-success-10": _training(trim_after_success=10),
    "keep-after-success": _training(trim_after_success=-1),  # every frame after success, as before
    "no-shift": _training(augment_shift=0.0),  # training windows not moved in space (before the 2 cm shift)
    "diffusion-epsilon": _policy(diffusion_prediction="epsilon"),  # for --algo dp3
    "cfg-amplify": _policy(cfg_guidance="amplify"),  # for the CFG variants
    "previous-preset": _previous_preset,
}


@dataclass(frozen=True)
class AblationConfig:
    """One ablation run."""

    data: str
    task: str
    change: str = "none"
    algo: str = "mp1"
    seed: int = 0
    world_model: str | None = None
    holdout_episodes: int = 1
    episodes: int = 100
    eval_seed: int = 100_000
    threads: int = 1
    workdir: str = "outputs/bench_ablation"


def run(config: AblationConfig) -> dict[str, object]:
    """Train, check perception, evaluate; returns (and stores) the figures."""
    if config.change not in CHANGES:
        raise ValueError(f"unknown change {config.change!r}; choose one of {list(CHANGES)}")
    name = f"{config.task}_{config.change}_{config.algo}_s{config.seed}"
    result_path = Path(config.workdir) / f"{name}.json"
    if result_path.exists():
        return json.loads(result_path.read_text())
    base = TrainPolicyConfig(data=config.data, out=str(Path(config.workdir) / "runs" / name), seed=config.seed,
                             world_model=config.world_model, holdout_episodes=config.holdout_episodes,
                             eval_episodes=0, threads=config.threads)
    train = CHANGES[config.change](dataclasses.replace(base, policy=dataclasses.replace(base.policy, algo=config.algo)))
    started = time.perf_counter()
    train_policy(train)
    train_seconds = time.perf_counter() - started
    checkpoint = Path(train.out) / CHECKPOINT_NAME
    evaluation = evaluate_checkpoint(checkpoint, config.task, config.episodes, config.eval_seed, end_on_success=True)
    check = load_checkpoint(checkpoint, "policy")["reliance"][-1]
    figures = {**dataclasses.asdict(config), "wins": sum(evaluation.successes), "episodes": evaluation.episodes,
               "train_seconds": train_seconds, "samples": train.steps * train.batch_size, "reliance": check}
    atomic_write_text(result_path, json.dumps(figures, indent=1))
    print(evaluation.summary())
    return figures


def table(workdir: str) -> str:
    """Markdown over every stored run, pooled over seeds per (task, change, algo)."""
    runs = [json.loads(path.read_text()) for path in sorted(Path(workdir).glob("*.json"))]
    groups: dict[tuple[str, str, str], list[dict]] = {}
    for figures in runs:
        groups.setdefault((figures["task"], figures["change"], figures["algo"]), []).append(figures)
    lines = ["| task | change | algo | seeds | success % [95 %] | per seed | clouds shuffled x | state shuffled x "
             "| train min |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for (task, change, algo), group in groups.items():
        wins, episodes = sum(g["wins"] for g in group), sum(g["episodes"] for g in group)
        rate, low, high = honest_protocol([True] * wins + [False] * (episodes - wins))
        per_seed = " / ".join(f"{100 * g['wins'] / g['episodes']:.0f}" for g in group)
        ratios = [g["reliance"] for g in group]
        cloud = " / ".join("-" if r["clouds_shuffled"] is None else f"{r['clouds_shuffled'] / r['intact']:.1f}"
                           for r in ratios)
        state = " / ".join(f"{r['state_shuffled'] / r['intact']:.1f}" for r in ratios)
        minutes = " / ".join(f"{g['train_seconds'] / 60:.1f}" for g in group)
        interval = f"{100 * rate:.0f} [{100 * low:.0f}-{100 * high:.0f}]"
        lines.append(f"| {task} | {change} | {algo} | {len(group)} | {interval} | {per_seed} | {cloud} | {state} "
                     f"| {minutes} |")
    return "\n".join(lines)
