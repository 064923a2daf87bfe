"""Pictures of point clouds and their crop box, to check cameras and boxes at a glance."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from d2a_envs.sampling import CropBox  # noqa: E402

# (elevation, azimuth, title) of the views drawn side by side.
_VIEWS = ((25, -60, "perspective"), (90, -90, "top (x-y)"), (0, -90, "front (x-z)"), (0, 0, "side (y-z)"))


def _box_edges(box: CropBox) -> list[np.ndarray]:
    low, high = np.array(box.low), np.array(box.high)
    corners = np.array([[(low, high)[i][0], (low, high)[j][1], (low, high)[k][2]]
                        for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    return [corners[[a, b]] for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]


def plot_point_cloud(
    raw: np.ndarray,
    sampled: np.ndarray,
    box: CropBox,
    title: str,
    out: str | Path,
) -> Path:
    """Save a figure with several views: every seen point (grey), the sampled cloud (coloured
    by height) and the crop box (red). Returns the written path."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig = plt.figure(figsize=(5 * len(_VIEWS), 5.4))
    # Show the surroundings of the box, not the far walls and floor.
    margin = 0.5 * (np.array(box.high) - np.array(box.low))
    near = np.all((raw[:, :3] > np.array(box.low) - margin) & (raw[:, :3] < np.array(box.high) + margin), axis=1)
    context = raw[near]
    for index, (elevation, azimuth, name) in enumerate(_VIEWS, start=1):
        ax = fig.add_subplot(1, len(_VIEWS), index, projection="3d")
        ax.scatter(*context[:, :3].T, s=0.3, c="0.75", alpha=0.4, depthshade=False)
        ax.scatter(*sampled[:, :3].T, s=1.5, c=sampled[:, 2], cmap="viridis", depthshade=False)
        for edge in _box_edges(box):
            ax.plot(*edge.T, color="red", linewidth=0.8)
        ax.view_init(elev=elevation, azim=azimuth)
        ax.set_xlabel("x"), ax.set_ylabel("y"), ax.set_zlabel("z")
        ax.set_aspect("equal")
        ax.set_title(name)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def plot_task_point_cloud(task: str, out: str | Path, seed: int = 0, steps: int = 0, **env_kwargs: object) -> Path:
    """Reset a D2A task (optionally take random steps) and save :func:`plot_point_cloud`."""
    import gymnasium as gym

    from d2a_envs.tasks import get_task

    spec = get_task(task)
    env = gym.make(spec.env_id, **env_kwargs)
    try:
        observation, info = env.reset(seed=seed)
        env.action_space.seed(seed)
        for _ in range(steps):
            observation, *_, info = env.step(env.action_space.sample())
        wrapper = env.get_wrapper_attr("sensor")
        base = env.unwrapped
        raw = wrapper.fused_points(base.model, base.data)
        config = wrapper.config
        title = (f"{spec.env_id}  seed={seed}  cameras={','.join(config.cameras)}  {config.backend} "
                 f"{config.image_size[0]}x{config.image_size[1]}  in crop: {info['num_points_in_crop']}"
                 f" -> N={config.num_points}")
        return plot_point_cloud(raw, observation["point_cloud"], config.crop_box, title, out)
    finally:
        env.close()


def plot_imagination(
    frames: list[dict[str, np.ndarray]], horizon: int, title: str, out: str | Path, box: CropBox
) -> Path:
    """One panel per frame: current cloud (opaque blue), imagined cloud (translucent orange)
    and the true cloud ``horizon`` steps later (translucent green), as in the paper's Fig. 3.

    Each frame is a dict with ``step``, ``current``, ``imagined``, ``future`` and the Chamfer
    distances ``imagined_error`` and ``persistence_error`` shown in its title."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig = plt.figure(figsize=(4.6 * len(frames), 5))
    for index, frame in enumerate(frames, start=1):
        ax = fig.add_subplot(1, len(frames), index, projection="3d")
        ax.scatter(*frame["current"][:, :3].T, s=2, c="tab:blue", alpha=0.8, depthshade=False, label="current")
        ax.scatter(*frame["imagined"][:, :3].T, s=2, c="tab:orange", alpha=0.25, depthshade=False, label="imagined")
        ax.scatter(*frame["future"][:, :3].T, s=1, c="tab:green", alpha=0.25, depthshade=False,
                   label=f"true t+{horizon}")
        for edge in _box_edges(box):
            ax.plot(*edge.T, color="red", linewidth=0.5)
        ax.view_init(elev=25, azim=-60)
        ax.set_aspect("equal")
        ax.set_title(f"t = {frame['step']}\nChamfer imagined {frame['imagined_error'] * 100:.1f} cm, "
                     f"copy-now {frame['persistence_error'] * 100:.1f} cm", fontsize=9)
        if index == 1:
            ax.legend(loc="upper left", fontsize=8, markerscale=4)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
