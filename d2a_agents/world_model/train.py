"""Train the triplane world model on stored demonstrations (``d2a train-wm``).

Held-out episodes (the last ``holdout_fraction`` of each task's episodes, at least one)
never enter training; they give the validation metrics. With ``demos``, the model trains on
the first ``demos`` episodes of each task, as a policy trained on them, and validates on the
episodes that follow them where the data set has more. Checkpoints are written
atomically every ``checkpoint_every`` steps and carry the model config, the voxel grid,
the tasks and the env kwargs; re-running the same command resumes from the last one.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
from tqdm import tqdm

from collectors.atomic import exclusive_writer
from collectors.storage import DemoDataset
from d2a_agents.checkpoint import load_for_resume, save_checkpoint
from d2a_agents.world_model.data import WorldModelTransitions
from d2a_agents.world_model.imagine import CHECKPOINT_KIND, logit, predict_grid, predict_logits
from d2a_agents.world_model.losses import balanced_queries, focal_loss
from d2a_agents.world_model.metrics import IoUAccumulator
from d2a_agents.world_model.triplane import CPU_PRESET, TriplaneWorldModel, WorldModelConfig
from d2a_agents.world_model.voxels import VoxelGrid
from d2a_envs.sampling import CropBox
from d2a_envs.tasks import get_task

# TrainWorldModelConfig fields a resumed run may change; the others must match the checkpoint's.
RESUMABLE_CHANGES = ("out", "model", "steps", "validate_every", "validation_stride", "checkpoint_every", "device",
                     "threads", "progress")


@dataclass(frozen=True)
class TrainWorldModelConfig:
    """Every knob of ``d2a train-wm`` (model sizes live in ``model``)."""

    data: str
    out: str
    model: WorldModelConfig = CPU_PRESET
    steps: int = 2000
    batch_size: int = 4
    learning_rate: float = 1e-3
    queries: int = 8192
    near_distance: int = 5
    focal_alpha: float | None = None  # balanced queries already balance the classes
    focal_gamma: float = 2.0
    holdout_fraction: float = 0.2
    demos: int | None = None  # train on the first demos episodes of each task (None: all but the held-out ones)
    # Also train on the data set's rollouts (noisy expert episodes, kept whole: d2a collect
    # --action-noise --keep-failures), states off the demonstrations a policy may reach.
    with_rollouts: bool = False
    validate_every: int = 500
    validation_stride: int = 5  # evaluate every k-th held-out transition
    checkpoint_every: int = 100
    seed: int = 0
    device: str = "cpu"  # "cuda" trains on a GPU (the paper preset's 128x128x32 grid)
    threads: int = 0  # torch threads; 0: leave torch's setting
    progress: bool = True
    crop_box: tuple[tuple[float, ...], tuple[float, ...]] | None = field(default=None)  # default: the suite's

    def __post_init__(self) -> None:
        for name in ("steps", "batch_size", "queries", "validate_every", "validation_stride", "checkpoint_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, not {getattr(self, name)}")
        if not self.learning_rate > 0:
            raise ValueError(f"learning_rate must be positive, not {self.learning_rate}")
        if self.threads < 0:
            raise ValueError(f"threads must not be negative, not {self.threads}")
        if self.demos is not None and self.demos < 1:
            raise ValueError(f"demos must be at least 1, not {self.demos}")
        if not 0 < self.holdout_fraction < 1:
            raise ValueError(f"holdout_fraction must lie in (0, 1), not {self.holdout_fraction}")


@dataclass
class ValidationResult:
    """Accumulated held-out metrics of the model and of the persistence baseline."""

    step: int
    full_iou: float
    dynamic_iou: float
    persistence_full_iou: float
    transitions: int
    threshold: float = 0.5


def split_episodes(
    dataset: DemoDataset, holdout_fraction: float, demos: int | None = None
) -> tuple[list[int], list[int]]:
    """(train, held-out) episode ids: the last ``holdout_fraction`` of each task's episodes;
    with ``demos``, training on the first ``demos`` of each task and holding out that fraction
    of ``demos`` from the episodes after them (from the first ``demos`` where there are none)."""
    train, held_out = [], []
    for task in dataset.metadata.tasks:
        ids = [e.index for e in dataset.metadata.episodes if e.task == task]
        if demos is not None and demos > len(ids):
            raise ValueError(f"{dataset.directory} holds {len(ids)} {task} episodes, fewer than demos={demos}")
        if demos is not None and demos < len(ids):
            train += ids[:demos]
            held_out += ids[demos : demos + max(1, round(demos * holdout_fraction))]
            continue
        n_held = max(1, round(len(ids) * holdout_fraction)) if len(ids) > 1 else 0
        train += ids[: len(ids) - n_held]
        held_out += ids[len(ids) - n_held :]
    if not train or not held_out:
        raise ValueError(f"{dataset.directory} needs at least two episodes per task to hold one out")
    return train, held_out


def dataset_crop_box(dataset: DemoDataset) -> CropBox:
    """The workspace box the data was collected with (all tasks must share one suite)."""
    import d2a_envs

    suites = {get_task(task).suite for task in dataset.metadata.tasks}
    if len(suites) != 1:
        raise ValueError(f"tasks of several suites {sorted(suites)} cannot share one voxel grid")
    boxes = {d2a_envs.env_crop_box(task, kwargs) for task, kwargs in dataset.metadata.tasks.items()}
    if len(boxes) != 1:
        raise ValueError(f"the tasks of this data set use different crop boxes: {sorted(map(str, boxes))}")
    return boxes.pop()


CANDIDATE_THRESHOLDS = (0.5, 0.6, 0.7, 0.8, 0.9)


@torch.no_grad()
def validate(
    model: TriplaneWorldModel, transitions: WorldModelTransitions, stride: int, step: int, threshold: float
) -> ValidationResult:
    """Full-grid and dynamic IoU at ``threshold`` over every ``stride``-th held-out transition."""
    model.eval()
    ours, persistence = IoUAccumulator(), IoUAccumulator()
    indices = torch.arange(0, len(transitions), stride)
    for chunk in indices.split(8):
        batch = transitions.get(chunk)
        ours.update(batch.current, predict_grid(model, batch.current, batch.actions, threshold), batch.target)
        persistence.update(batch.current, batch.current, batch.target)
    model.train()
    return ValidationResult(step, ours.full_iou, ours.dynamic_iou, persistence.full_iou, len(indices), threshold)


@torch.no_grad()
def calibrate_threshold(model: TriplaneWorldModel, transitions: WorldModelTransitions, samples: int = 64) -> float:
    """The occupancy threshold with the best full-grid IoU on TRAINING transitions.

    Balanced queries show the decoder far more occupied voxels than the grid holds, so its
    probabilities run high and 0.5 over-predicts; the threshold is chosen on training data,
    never on the held-out episodes it is then evaluated on.
    """
    model.eval()
    accumulators = {threshold: IoUAccumulator() for threshold in CANDIDATE_THRESHOLDS}
    for chunk in torch.linspace(0, len(transitions) - 1, samples).long().split(8):
        batch = transitions.get(chunk)
        logits = predict_logits(model, batch.current, batch.actions)
        for threshold, accumulator in accumulators.items():
            accumulator.update(batch.current, logits > logit(threshold), batch.target)
    model.train()
    return max(accumulators, key=lambda threshold: accumulators[threshold].full_iou)


def _payload(config: TrainWorldModelConfig, dataset: DemoDataset, grid: VoxelGrid) -> dict:
    return {
        "config": config.model.to_dict(),
        "grid": {"box": {"low": grid.box.low, "high": grid.box.high}, "resolution": list(grid.resolution)},
        "tasks": sorted(dataset.metadata.tasks),
        "env_kwargs": dataset.metadata.tasks,
        "num_points": int(dataset.frames()["point_cloud"].shape[1]),
        "train_config": {k: v for k, v in dataclasses.asdict(config).items() if k != "model"},
        "run_config": {k: v for k, v in dataclasses.asdict(config).items() if k not in RESUMABLE_CHANGES},
    }


def train_world_model(config: TrainWorldModelConfig) -> tuple[TriplaneWorldModel, list[ValidationResult]]:
    """Train (or resume) and return the model (on the CPU) and its validation history.

    The checkpoint file is locked for the whole run: a second trainer into it is refused.
    """
    out = Path(config.out)
    with exclusive_writer(out.parent, lock_name=f".{out.name}.lock"):
        return _train_world_model(config)


def _train_world_model(config: TrainWorldModelConfig) -> tuple[TriplaneWorldModel, list[ValidationResult]]:
    if config.threads:
        torch.set_num_threads(config.threads)
    device = torch.device(config.device)
    full = DemoDataset.open_for_training(config.data)
    dataset = full.demonstrations()
    if dataset.holds_exactly(config.demos):
        config = dataclasses.replace(config, demos=None)  # every episode: recorded as a run on the whole set
    box = CropBox.from_any(config.crop_box) if config.crop_box is not None else dataset_crop_box(dataset)
    grid = VoxelGrid(box, config.model.resolution)
    action_dim = int(dataset.frames()["action"].shape[-1])
    model_config = dataclasses.replace(config.model, action_dim=action_dim)
    config = dataclasses.replace(config, model=model_config)
    train_ids, held_out_ids = split_episodes(dataset, config.holdout_fraction, config.demos)
    if config.with_rollouts:
        rollouts = full.rollout_episodes()
        if not rollouts:
            raise ValueError(f"{config.data} holds no rollouts: collect them with d2a collect --action-noise "
                             "--keep-failures --append (the noisy expert's) or --policy --append (a policy's)")
        train_ids += rollouts
    frames = full.frames()
    train = WorldModelTransitions(frames, grid, model_config.horizon, model_config.action_history, train_ids)
    held_out = WorldModelTransitions(frames, grid, model_config.horizon, model_config.action_history, held_out_ids)
    if config.batch_size > len(train):
        raise ValueError(f"batch size {config.batch_size} exceeds the {len(train)} training transitions of "
                         f"{config.data}: draws would repeat within a batch; lower --batch-size")

    torch.manual_seed(config.seed)
    model = TriplaneWorldModel(model_config).to(device)
    optimizer = torch.optim.AdamW(model.parameters(), lr=config.learning_rate)
    generator = torch.Generator().manual_seed(config.seed)
    payload = _payload(config, dataset, grid)
    start, history = 0, []
    out = Path(config.out)
    previous = load_for_resume(out, CHECKPOINT_KIND, payload, ("config", "grid", "tasks", "run_config"),
                               upgrades={"config": lambda raw: WorldModelConfig.from_dict(raw).to_dict()})
    if previous is not None:
        model.load_state_dict(previous["model"])
        optimizer.load_state_dict(previous["optimizer"])
        generator.set_state(previous["generator"])
        start, history = previous["step"], [ValidationResult(**v) for v in previous["history"]]

    def checkpoint(step: int) -> None:
        save_checkpoint(out, CHECKPOINT_KIND, {
            **payload, "model": model.state_dict(), "optimizer": optimizer.state_dict(),
            "generator": generator.get_state(), "step": step, "history": [dataclasses.asdict(v) for v in history],
            "threshold": history[-1].threshold if history else 0.5,
        })

    resolution = torch.tensor(model_config.resolution, dtype=torch.float32)
    bar = tqdm(range(start, config.steps), initial=start, total=config.steps, desc="world model",
               disable=not config.progress)
    started = time.perf_counter()
    for step in bar:
        batch = train.sample(config.batch_size, generator)
        indices, labels = balanced_queries(batch.target, config.queries, config.near_distance, generator)
        queries = (indices.float() + 0.5) / resolution * 2.0 - 1.0
        logits = model(batch.current.to(device), batch.actions.to(device), queries.to(device))
        loss = focal_loss(logits, labels.to(device), alpha=config.focal_alpha, gamma=config.focal_gamma)
        if not torch.isfinite(loss):
            raise FloatingPointError(f"the world-model loss became {loss.item()} at step {step + 1}; "
                                     f"{out} keeps the last finite checkpoint")
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        bar.set_postfix(loss=f"{loss.item():.4f}")
        done = step + 1
        if done % config.validate_every == 0 or done == config.steps:
            threshold = calibrate_threshold(model, train)
            result = validate(model, held_out, config.validation_stride, done, threshold)
            history.append(result)
            bar.write(f"step {done}: held-out IoU {result.full_iou:.3f} "
                      f"(persistence {result.persistence_full_iou:.3f}), dynamic IoU {result.dynamic_iou:.3f}, "
                      f"threshold {threshold} (chosen on training data)")
        if done % config.checkpoint_every == 0 or done == config.steps:
            checkpoint(done)
    bar.close()
    if start >= config.steps and not history:
        history.append(validate(model, held_out, config.validation_stride, start, calibrate_threshold(model, train)))
    if config.progress:
        print(f"trained {config.steps - start} steps in {time.perf_counter() - started:.0f} s "
              f"({torch.get_num_threads()} thread(s), {device}) -> {out}")
    return model.cpu(), history
