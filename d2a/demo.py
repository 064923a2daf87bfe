"""The end-to-end demo (``d2a demo``, what ``make demo`` runs) on an embedded default.

Meta-World Hammer: collect scripted-expert demonstrations, train the triplane world model,
train the D2A policy on current + imagined clouds, evaluate it, print success, the
perception check and IoU, and write the imagination picture and the training curves. The
default sizes fit a 2-core CPU: they give up resolution (32 x 32 x 8 voxels, 64 points per
cloud, narrow networks) and training length against the paper's GPU settings.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from collectors.collect import CollectConfig, collect
from d2a_agents.policy.checkpoints import CHECKPOINT_NAME, evaluate_checkpoint
from d2a_agents.policy.train import POLICY_PRESETS, PolicyPreset, TrainPolicyConfig, train_policy
from d2a_agents.training_plots import plot_training_curves
from d2a_agents.world_model.train import TrainWorldModelConfig, train_world_model
from d2a_agents.world_model.triplane import WorldModelConfig
from d2a_agents.world_model.viz import plot_task_imagination


@dataclass(frozen=True)
class DemoConfig:
    """Every setting of the demo (CPU-sized defaults)."""

    task: str = "hammer"
    out: str = "outputs/demo"
    episodes: int = 10
    seed: int = 0
    world_model: WorldModelConfig = WorldModelConfig(resolution=(32, 32, 8))
    world_model_steps: int = 300
    policy: PolicyPreset = POLICY_PRESETS["cpu"]  # architecture and training budget
    eval_episodes: int = 20
    eval_workers: int = 1
    # torch threads of both trainings (0: torch's own, every core). Alone on a 2-core machine
    # two threads train the demo's policy in 198 s, one in 292 s; beside other busy work, use 1.
    threads: int = 0
    env_kwargs: dict[str, object] = field(default_factory=dict)  # gym.make options: image_size, num_points...


def run_demo(config: DemoConfig = DemoConfig()) -> dict[str, float]:
    """Run the whole pipeline; returns the headline figures."""
    out = Path(config.out)
    data, world_model = out / "data", out / "world_model.pt"
    print(f"1/4 collecting {config.episodes} {config.task} demonstrations")
    collect(CollectConfig(tasks=(config.task,), out=str(data), episodes=config.episodes, seed=config.seed,
                          env_kwargs=config.env_kwargs, append=True))
    print("2/4 training the world model")
    _, wm_history = train_world_model(TrainWorldModelConfig(
        data=str(data), out=str(world_model), model=config.world_model, steps=config.world_model_steps,
        validate_every=max(1, config.world_model_steps // 3), validation_stride=2, seed=config.seed,
        threads=config.threads,
    ))
    print("3/4 training the policy")
    preset = config.policy
    run = out / preset.policy.algo
    train_policy(TrainPolicyConfig.from_preset(
        preset, data=str(data), out=str(run), world_model=str(world_model), eval_episodes=0, seed=config.seed,
        threads=config.threads,
    ))
    print(f"4/4 evaluating on {config.eval_episodes} new layouts")
    result = evaluate_checkpoint(run / CHECKPOINT_NAME, config.task, config.eval_episodes, seed=100_000,
                                 workers=config.eval_workers, end_on_success=True)
    picture = plot_task_imagination(world_model, config.task, out / "imagination.png", seed=config.seed,
                                    **config.env_kwargs)
    curves = plot_training_curves(run / CHECKPOINT_NAME, world_model, out / "training_curves.png", result)
    last = wm_history[-1]
    print(result.summary())
    print(f"world model, held-out: full-grid IoU {last.full_iou:.3f} (persistence {last.persistence_full_iou:.3f}), "
          f"dynamic IoU {last.dynamic_iou:.3f}, threshold {last.threshold}")
    print(f"wrote {picture} and {curves}")
    return {"success_rate": result.success_rate, "full_iou": last.full_iou, "dynamic_iou": last.dynamic_iou}

