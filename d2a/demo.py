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

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

from collectors.collect import CollectConfig, collect  # noqa: E402
from collectors.evaluation import EvaluationResult  # noqa: E402
from d2a_agents.checkpoint import load_checkpoint  # noqa: E402
from d2a_agents.policy.train import (  # noqa: E402
    CHECKPOINT_NAME,
    POLICY_PRESETS,
    PolicyPreset,
    TrainPolicyConfig,
    evaluate_checkpoint,
    train_policy,
)
from d2a_agents.world_model.train import TrainWorldModelConfig, train_world_model  # noqa: E402
from d2a_agents.world_model.triplane import WorldModelConfig  # noqa: E402
from d2a_agents.world_model.viz import plot_task_imagination  # noqa: E402


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
    env_kwargs: dict[str, object] = field(default_factory=dict)  # gym.make options: image_size, num_points...


def _running_mean(values: list[float], window: int) -> torch.Tensor:
    """Mean over the last ``window`` values at each step (the raw values when there are fewer)."""
    values = torch.tensor(values)
    return values.unfold(0, window, 1).mean(1) if len(values) >= window else values


def plot_training_curves(
    policy_checkpoint: Path, world_model_checkpoint: Path, out: Path, final: EvaluationResult | None = None
) -> Path:
    """Policy loss (with its evaluations, and ``final`` at the last step), the adaptive-CFG
    gate when the policy has one, and the world model's held-out IoU, side by side."""
    policy, world_model = load_checkpoint(policy_checkpoint, "policy"), load_checkpoint(world_model_checkpoint,
                                                                                         "world_model")
    metrics = policy["metrics"]
    has_gate = "cfg_weight" in metrics[0]
    fig, axes = plt.subplots(1, 3 if has_gate else 2, figsize=(16 if has_gate else 11, 4))
    loss_axis, wm_axis = axes[0], axes[-1]
    steps = [row["step"] for row in metrics]
    window = max(1, len(steps) // 50)
    losses = [row["mse"] for row in metrics]
    smooth = _running_mean(losses, window)
    loss_axis.plot(steps, losses, alpha=0.3, label="training MSE")
    loss_axis.plot(steps[-len(smooth):], smooth, label=f"training MSE ({window}-step mean)")
    loss_axis.set_yscale("log")
    loss_axis.set_xlabel("policy step")
    loss_axis.set_title(f"{policy['policy_config']['algo']} policy")
    points = [(point["step"], point["success_rate"], point["episodes"]) for point in policy["history"]]
    if final is not None:
        points.append((steps[-1], final.success_rate, final.episodes))
    for step, rate, episodes in points:
        loss_axis.annotate(f"success {rate:.0%} of {episodes}", (step, smooth[-1].item()), ha="right")
    loss_axis.legend()
    if has_gate:
        gate_axis = axes[1]
        for key, label in (("cfg_weight", "gate w (batch mean)"), ("cfg_rho", "cosine rho (batch mean)"),
                           ("cfg_active", "fraction with w < 1")):
            curve = _running_mean([row[key] for row in metrics], window)
            gate_axis.plot(steps[-len(curve):], curve, label=f"{label}, {window}-step mean")
        tau_l, tau_h = policy["policy_config"]["cfg_thresholds"]
        for tau in (tau_l, tau_h):
            gate_axis.axhline(tau, color="grey", linestyle=":", linewidth=1)
        gate_axis.set_xlabel("policy step")
        gate_axis.set_title(f"adaptive CFG, eq. 7 (tau = {tau_l:g} / {tau_h:g}, dotted)")
        gate_axis.legend()
    history = world_model["history"]
    wm_axis.plot([h["step"] for h in history], [h["full_iou"] for h in history], "o-", label="triplane full-grid IoU")
    wm_axis.plot([h["step"] for h in history], [h["dynamic_iou"] for h in history], "o-", label="triplane dynamic IoU")
    wm_axis.plot([h["step"] for h in history], [h["persistence_full_iou"] for h in history], "k--",
                 label="persistence full-grid IoU")
    wm_axis.set_xlabel("world-model step")
    wm_axis.set_title("world model, held-out episodes")
    wm_axis.legend()
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


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
    ))
    print("3/4 training the policy")
    preset = config.policy
    run = out / preset.policy.algo
    train_policy(TrainPolicyConfig(
        data=str(data), out=str(run), policy=preset.policy, world_model=str(world_model), steps=preset.steps,
        batch_size=preset.batch_size, learning_rate=preset.learning_rate, eval_episodes=0, seed=config.seed,
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

