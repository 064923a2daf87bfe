"""Training curves of a D2A run: the policy's loss and evaluations, its adaptive-CFG gate, and
the world model's held-out IoU, in one figure (what ``d2a demo`` writes)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only; no display needed

import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

from collectors.evaluation import EvaluationResult  # noqa: E402
from d2a_agents.checkpoint import load_checkpoint  # noqa: E402


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
