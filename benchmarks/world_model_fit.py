"""Does a world model imagine its training demonstrations better than new ones? (``d2a bench wm-fit``)

A ``d2a`` policy trains on the world model's imaginations of the demonstrations the model itself
trained on, and acts on imaginations of scenes the model never saw. If the model fits its own
episodes much better, the policy learns to trust a cloud better than the one it will act on;
imagining each episode with a model that did not train on it (cross-fitting) would close that
gap. This bench measures it: full-grid and dynamic IoU, and the imagined cloud's Chamfer
distance to the true cloud H steps ahead, on the first ``demos`` episodes of each task and on
the episodes after them, each beside copying the present.

Example::

    run(WorldModelFitConfig(world_model="outputs/table4/world_models/lever-pull_d5.pt",
                            data="outputs/table4/data/lever-pull", demos=5))
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from collectors.storage import DemoDataset
from d2a_agents.world_model.data import WorldModelTransitions
from d2a_agents.world_model.evaluation import imagination_chamfer
from d2a_agents.world_model.imagine import Imaginer
from d2a_agents.world_model.train import validate


@dataclass(frozen=True)
class WorldModelFitConfig:
    """What ``d2a bench wm-fit`` measures."""

    world_model: str
    data: str
    demos: int  # the world model trained on the first demos episodes of each task
    stride: int = 5  # every stride-th transition of each split

    def __post_init__(self) -> None:
        if self.demos < 1 or self.stride < 1:
            raise ValueError(f"demos and stride must be at least 1, got {self.demos} and {self.stride}")


def run(config: WorldModelFitConfig) -> dict[str, dict[str, float]]:
    """Per split ("trained on", "unseen"): episodes, transitions, IoU (model, dynamic, persistence)
    and Chamfer distances in metres (``imagination_chamfer``'s keys, prefixed ``chamfer_``)."""
    dataset = DemoDataset.open_for_training(config.data)
    trained = [episode.index for episode in dataset.first_episodes(config.demos).metadata.episodes]
    unseen = [episode.index for episode in dataset.metadata.episodes[len(trained):]]  # the view leads the storage
    if not unseen:
        raise ValueError(f"{config.data} holds no episode after the first {config.demos} of each task")
    imaginer = Imaginer.from_checkpoint(config.world_model)
    frames, model = dataset.frames(), imaginer.config
    print(f"\n{Path(config.world_model).name} on {config.data}: every {config.stride}th transition, H = "
          f"{model.horizon}; Chamfer to the true cloud H steps ahead in cm (a row as each split is measured)\n")
    print("| episodes | count | transitions | full IoU | dynamic IoU | persistence IoU | Chamfer imagined | "
          "Chamfer persistence |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |", flush=True)
    rows = {}
    for name, episodes in (("trained on", trained), ("unseen", unseen)):
        transitions = WorldModelTransitions(frames, imaginer.grid, model.horizon, model.action_history, episodes)
        iou = validate(imaginer.model, transitions, config.stride, 0, imaginer.threshold)
        chamfer = imagination_chamfer(Path(config.world_model), dataset, episodes, config.stride)
        row = rows[name] = dict(episodes=len(episodes), transitions=iou.transitions, full_iou=iou.full_iou,
                                dynamic_iou=iou.dynamic_iou, persistence_iou=iou.persistence_full_iou,
                                **{f"chamfer_{key}": value for key, value in chamfer.items()})
        print(f"| {name} | {row['episodes']} | {row['transitions']} | {row['full_iou']:.3f} | "
              f"{row['dynamic_iou']:.3f} | {row['persistence_iou']:.3f} | {100 * row['chamfer_imagined']:.2f} | "
              f"{100 * row['chamfer_persistence']:.2f} |", flush=True)
    return rows
