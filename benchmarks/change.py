"""Where the scene will change, as each cloud a policy could read shows it (``d2a bench change``).

For a trained world model on its demonstrations: the imagined change cloud (what ``d2a-change``
reads) against the change the observation history already shows (motion continued), the
present cloud (what ``d2a-present`` reads) and the true change resampled (the floor), at the
policy's point count, on demonstrations the world model did not train on, or on the states a
policy reaches (its rollouts, ``d2a collect --policy``, with ``demos=0``). Prints a markdown
table of mean distances (cm): from the cloud to the true change (precision) and back (coverage).

Example::

    run(ChangeBenchConfig(world_model="outputs/table4/world_models/push_d5.pt", data="outputs/table4/data/push",
                          demos=5))
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from collectors.storage import DemoDataset
from d2a_agents.world_model.evaluation import change_distances
from d2a_agents.world_model.train import split_episodes


@dataclass(frozen=True)
class ChangeBenchConfig:
    """What ``d2a bench change`` measures."""

    world_model: str
    data: str
    # The world model trained on the first demos of each task: measure on the rest (0: on every
    # episode, e.g. a policy's own rollouts from d2a collect --policy; None: its held-out split).
    demos: int | None = None
    stride: int = 2  # every stride-th held-out transition
    num_points: int = 64  # the policy's point count


def held_out_episodes(dataset: DemoDataset, demos: int | None) -> list[int]:
    """Every episode after the first ``demos`` of each task, or the world model's own held-out ones."""
    if demos is None:
        return split_episodes(dataset, 0.2)[1]
    held = [ids[demos:] for ids in ([e.index for e in dataset.metadata.episodes if e.task == task]
                                    for task in dataset.metadata.tasks)]
    episodes = [index for ids in held for index in ids]
    if not episodes:
        raise ValueError(f"{dataset.directory} holds no episode after the first {demos} of each task")
    return episodes


def run(config: ChangeBenchConfig) -> dict[str, dict[str, float]]:
    dataset = DemoDataset.open_for_training(config.data)
    episodes = held_out_episodes(dataset, config.demos)
    result = change_distances(Path(config.world_model), dataset, episodes, config.stride, config.num_points)
    transitions = next(iter(result.values()))["transitions"]
    print(f"\n{Path(config.world_model).name} on {len(episodes)} held-out episodes of {config.data}, "
          f"{transitions:.0f} transitions where something newly fills, {config.num_points} points per cloud\n")
    print("| cloud | to the true change, cm (precision) | from the true change, cm (coverage) |")
    print("| --- | --- | --- |")
    for name, row in result.items():
        print(f"| {name} | {100 * row['precision']:.2f} | {100 * row['coverage']:.2f} |")
    return result
