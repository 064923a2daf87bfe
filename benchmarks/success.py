"""Success-rate benchmark (``d2a bench success``): policy variants side by side.

For each task: collect (or reuse) the expert demonstrations, train one world model that the
imagination variants share (on the same demonstrations as the policies), then for every
(variant, seed) train a policy on the same demos with the same budget, evaluate it periodically
during training (the paper's protocol: the mean of the top-5 evaluations) and evaluate its
final checkpoint on new layouts (the honest protocol: one checkpoint chosen in advance, a
Wilson interval). Prints a markdown table.

Every finished (task, variant, seed) is stored as ``cells/<task>_<algo>_s<seed>_e<N>.json``
(atomic write; N the number of periodic evaluations, ``_fresh`` for new layouts at each,
``_d<K>`` for K demonstrations other than 10, and a tag for any policy preset other than
``cpu``, so runs with other counts or budgets share the workdir's data and world models); a
rerun skips finished cells, completes a collection cut short and resumes an interrupted
training from its checkpoint and an interrupted final evaluation from its last finished
episode (``final_evaluation.jsonl`` in the run directory), so a long run can be killed and
restarted. Demonstrations
collected with other env settings are refused, not reused. ``cells`` may name another directory
for the cell files (for example one kept under version control, while data and checkpoints stay
in the workdir).

Several local processes may run the same bench in one workdir, one thread each: a process
claims a cell before it trains it (a lock the system releases when the process dies) and skips
cells another process holds; a task's demonstrations or world model being written by another
process are waited for, not written twice.

On Ray (``ray_address``), the demonstrations are collected as Ray jobs, each task's world model
is a job, and every unfinished cell is a job that asks for ``threads`` CPUs (and a GPU where
the cluster has one, training there); the driver writes each cell's file as it arrives, so the
directory and the table are those of a local run. A cell whose worker died on every retry is
reported as missing; a rerun resumes it from its checkpoint. The workdir must be readable and
writable on every node (one machine, or a shared filesystem).

Two presets: ``paper`` (the paper's protocol shape and the policy's full-size networks: 3
seeds, 15 evaluations of 20 episodes, 100 final episodes; GPU work) and ``cpu`` (the same
protocol shape with the ``cpu`` policy preset: 3 seeds, 5 evaluations of 20 episodes, 100 final
episodes; ``evaluations=15`` gives the paper's count). ``mp1-state``, the same action expert on
privileged state, is the perception reference: the gap between it and ``mp1`` is what
perception costs.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import re
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from tqdm import tqdm

import d2a_envs
from benchmarks.cells import DEFAULT_DEMOS, Cell, read_cell, summarize
from collectors.atomic import DirectoryBusyError, atomic_write_text, exclusive_writer
from collectors.collect import DART_MAX_ATTEMPTS_FACTOR, CollectConfig, collect, demonstrations_tag
from collectors.experts import ExpertSettings, Student
from collectors.ray_jobs import JobsLost, Lost, as_completed, cluster_gpus, ray_cluster
from d2a_agents.checkpoint import load_checkpoint
from d2a_agents.policy.agent import reads_images, uses_imagination
from d2a_agents.policy.checkpoints import CHECKPOINT_NAME, Acting, checkpoint_student, evaluate_checkpoint
from d2a_agents.policy.train import EVALUATION_SEED, POLICY_PRESETS, PolicyPreset, TrainPolicyConfig, train_policy
from d2a_agents.success_plot import SuccessBar, plot_success_bars
from d2a_agents.world_model.train import TrainWorldModelConfig, train_world_model
from d2a_agents.world_model.triplane import CPU_PRESET, WorldModelConfig
from d2a_envs.gl import software_render_threads

# The paper's MP1 / D2A success (%): Table IV (Meta-World, 10 demonstrations; no Hammer
# column) and Table I's Adroit columns.
PAPER_REFERENCE = {
    "lever-pull": (81, 85), "assembly": (98, 100), "push": (74, 85), "stick-pull": (74, 81),
    "adroit-hammer": (100, 100), "adroit-door": (69, 74), "adroit-pen": (58, 63),
}

FINAL_JOURNAL = "final_evaluation.jsonl"  # in the run directory: the final evaluation's finished episodes
ROLLOUT_SEED = 50_000  # first layout of the world model's rollouts: apart from demonstrations and evaluations


@dataclass(frozen=True)
class SuccessBenchConfig:
    """What ``d2a bench success`` runs (defaults: the ``cpu`` preset)."""

    tasks: tuple[str, ...] = ("hammer", "lever-pull", "assembly", "push", "stick-pull")
    algos: tuple[str, ...] = ("d2a", "d2a-no-cfg", "mp1", "dp3", "mp1-state")
    seeds: tuple[int, ...] = (0, 1, 2)
    demos: int = DEFAULT_DEMOS  # per cell: the first ``demos`` of one collection per task
    # Demonstrations collected per task (default: demos). A workdir whose cells train on several
    # counts collects the largest once, so that 1 of 2 of 5 ... are nested and each world model
    # trains on its policies' demonstrations and validates on the ones after them.
    pool: int | None = None
    # Env seed of the pool's first attempt (its layouts): another seed, another set of
    # demonstrations with its own data set, world models and cells (``_pool<seed>``), to see
    # whether a finding outlives the one set. 0 or, clear of pool 0's and the periodic
    # evaluations' layouts (EVALUATION_SEED on), from pool x DART_MAX_ATTEMPTS_FACTOR on.
    demo_seed: int = 0
    # Noisy expert rollouts per task (kept whole, seeds from ROLLOUT_SEED) that the world model
    # trains on beside the demonstrations (0: none); imagining cells then carry ``_wmr<N>``.
    wm_rollouts: int = 0
    rollout_noise: float = 0.3
    # The algo of this bench's own cell of seed ``wm_policy_seed`` (same task, demonstrations and
    # settings, the plain world model) whose own rollouts, not the noisy expert's, are those
    # ``wm_rollouts``: a world model that has seen the states such a policy reaches; its data,
    # world model and imagining cells carry ``_wmr<N>p<algo>`` (``...p<algo>s<seed>`` for a seed
    # other than 0). None: the noisy expert's.
    wm_policy_rollouts: str | None = None
    wm_policy_seed: int = 0
    # DART noise of the demonstrations (d2a collect --dart-noise): their own data set, world
    # models and cells (``_dart<std>``); 0: plain demonstrations.
    dart_noise: float = 0.0
    # The Adroit expert of the demonstrations and rollouts (d2a collect --expert: controller or
    # planner): their own data set, world models and cells (``_<kind>``); None: the task's default.
    expert: str | None = None
    # Every evaluation (periodic and final) acts on the mean of this many chunks per plan
    # (d2a eval --action-draws; cells ``_draws<k>``): Adroit's DART policies need it.
    action_draws: int = 1
    workdir: str = "outputs/bench_success"
    cells: str | None = None  # directory of the finished cells' files (default: <workdir>/cells)
    policy: PolicyPreset = POLICY_PRESETS["cpu"]  # architecture and training budget of every variant
    evaluations: int = 5  # periodic evaluations during training, the last one at the final step
    eval_episodes: int = 20  # per periodic evaluation (the paper: 20)
    eval_layouts: str = "fixed"  # "fresh": new layouts at each periodic evaluation, as DP3 and MP1 (TrainPolicyConfig)
    final_episodes: int = 100  # extra evaluation of the final checkpoint; 0: reuse the last periodic one
    world_model: WorldModelConfig = WorldModelConfig(resolution=(32, 32, 8))
    world_model_steps: int = 300
    workers: int = 1  # evaluation worker processes of a local cell (a Ray cell evaluates in its own process)
    threads: int = 1  # torch threads of a cell's training; on Ray, the CPUs each cell asks for
    device: str = "cpu"  # of a local cell's training; a Ray cell trains on "cuda" when the cluster has a GPU
    ray_address: str | None = None  # "local", "auto" or a cluster address: run the cells on Ray
    final_seed: int = 100_000  # the extra final evaluation (periodic ones: train_policy's layouts)
    # gym.make options of the demonstrations (and so of every evaluation), e.g. the dense clouds
    # {"image_size": 256, "num_points": 4096, "backend": "render"} that the 128x128x32 world model reads.
    env_kwargs: dict[str, object] = field(default_factory=dict)
    # Directories of another grid's cells made from the same collections (the same tasks, seeds and
    # env settings: Table I's 10 demonstrations per task are the first 10 of Table IV's 20): a cell of
    # a method that reads no world model, found there under this grid's name, is copied rather than
    # rerun. Imagining cells are never copied: a world model's training split depends on how many
    # demonstrations its collection holds (d2a train-wm holds some out when there are no more).
    shared_cells: tuple[str, ...] = ()
    # Side in pixels of the camera images stored with the demonstrations when an algo reads them
    # (dp; DP3's Meta-World images are 84 pixels): their own data set (``_rgb<side>``), which
    # every algo of such a bench then trains on (the same demonstrations, images added).
    rgb_image_size: int = 84

    def __post_init__(self) -> None:
        if self.pool is not None and self.pool < self.demos:
            raise ValueError(f"a pool of {self.pool} demonstrations cannot give cells {self.demos}")
        span = (self.pool or self.demos) * DART_MAX_ATTEMPTS_FACTOR  # the most seeds a pool's attempts take
        if self.demo_seed and not span <= self.demo_seed <= EVALUATION_SEED - span:
            raise ValueError(f"demo_seed must be 0 or within {span}..{EVALUATION_SEED - span}, clear of pool 0's "
                             f"layouts and the periodic evaluations', not {self.demo_seed}")
        if self.action_draws < 1:
            raise ValueError(f"action_draws must be at least 1, not {self.action_draws}")
        if self.wm_policy_rollouts is not None and not self.wm_rollouts:
            raise ValueError("wm_policy_rollouts names whose rollouts the world model trains on: give their "
                             "count, wm_rollouts")
        if self.wm_policy_seed and self.wm_policy_rollouts is None:
            raise ValueError("wm_policy_seed picks the cell of wm_policy_rollouts whose rollouts the world model "
                             "trains on: name its algo")
        ExpertSettings(kind=self.expert)  # an unknown kind fails here
        others = [task for task in self.tasks if d2a_envs.get_task(task).suite != "adroit"]
        if self.expert is not None and others:
            raise ValueError(f"the expert ({self.expert}) applies to Adroit tasks; {others} have one expert each")


# The dense clouds that the 128x128x32 world model reads (and the Table IV benches used).
DENSE_CLOUDS: dict[str, object] = {"num_points": 4096, "image_size": 256, "backend": "render"}


def paper_table_cells(workdir: str) -> SuccessBenchConfig:
    """The per-cell settings of the paper-table grids (``d2a bench table1`` / ``table4``): the
    ``cpu`` policy preset on dense clouds, new layouts at each periodic evaluation as the
    paper's runners, the 128x128x32 world model of 2000 steps for the imagining variants."""
    return SuccessBenchConfig(tasks=(), algos=(), seeds=(), workdir=workdir, env_kwargs=DENSE_CLOUDS,
                              eval_layouts="fresh", world_model=CPU_PRESET, world_model_steps=2000)


PRESETS: dict[str, SuccessBenchConfig] = {
    "cpu": SuccessBenchConfig(),
    # Section IV of the paper: 20 episodes every 200 of 3000 epochs (15 evaluations), 3 seeds.
    # It gives no world-model budget; 20k steps of batch 4 is our choice.
    "paper": SuccessBenchConfig(
        policy=POLICY_PRESETS["paper"], evaluations=15, eval_layouts="fresh",
        world_model=WorldModelConfig(), world_model_steps=20_000,
    ),
}


Result = TypeVar("Result")


def _when_free(work: Callable[[], Result], what: str, poll_seconds: float = 10.0) -> Result:
    """``work()``, retried while another process holds the directory it writes (it then
    finds that process's finished result, or completes it)."""
    while True:
        try:
            return work()
        except DirectoryBusyError:
            print(f"{what}: another process is writing it; waiting", flush=True)
            time.sleep(poll_seconds)


def _data_env_kwargs(config: SuccessBenchConfig) -> dict[str, object]:
    """The env options of the bench's demonstrations: the config's, and images where an algo reads them."""
    images = any(map(reads_images, config.algos))
    return {**config.env_kwargs, **({"rgb_image_size": config.rgb_image_size} if images else {})}


def _dataset(config: SuccessBenchConfig, task: str) -> Path:
    """The task's demonstrations in the workdir: collected, or a collection cut short completed
    (``collect`` refuses a data set collected with other env settings)."""
    env_kwargs = _data_env_kwargs(config)
    images = f"_rgb{env_kwargs['rgb_image_size']}" if "rgb_image_size" in env_kwargs else ""
    data = Path(config.workdir) / "data" / f"{task}{_demonstrations_tag(config)}{images}"
    # Whose rollouts the world model also sees: a trained policy's (its own actions, collected
    # here) or the noisy expert's (on Ray where the bench runs there).
    source: dict[str, object] = dict(action_noise=config.rollout_noise, keep_failures=True,
                                     ray_address=config.ray_address)
    rollouts = f"{task} rollouts"
    if config.wm_policy_rollouts is not None:  # the pool again (the same seeds: the same episodes), apart
        data = data.with_name(f"{data.name}{_world_model_tag(config)}")
        student = _policy_student(config, task)
        source, rollouts = dict(student=student, student_labels=False), f"{rollouts} of {student.name}"
    _when_free(lambda: collect(CollectConfig(
        tasks=(task,), out=str(data), episodes=config.pool or config.demos, seed=config.demo_seed, append=True,
        env_kwargs=env_kwargs, dart_noise=config.dart_noise, expert=config.expert,
        progress=config.ray_address is None, ray_address=config.ray_address,
    )), f"{task} demonstrations")
    if config.wm_rollouts:
        _when_free(lambda: collect(CollectConfig(
            tasks=(task,), out=str(data), episodes=config.wm_rollouts, seed=ROLLOUT_SEED, append=True,
            env_kwargs=env_kwargs, expert=config.expert, progress=config.ray_address is None, **source,
        )), rollouts)
    return data


def _policy_student(config: SuccessBenchConfig, task: str) -> Student:
    """The trained policy of the plain bench's ``wm_policy_rollouts`` cell of seed ``wm_policy_seed``
    in the workdir (whichever results directory holds its cell), as the acting policy of the world
    model's rollouts; refused while its training is not finished."""
    plain = dataclasses.replace(config, wm_rollouts=0, wm_policy_rollouts=None, wm_policy_seed=0)
    algo, seed = config.wm_policy_rollouts, config.wm_policy_seed
    run = Path(plain.workdir) / "runs" / _cell_name(plain, task, algo, seed)
    if not (run / CHECKPOINT_NAME).exists() or load_checkpoint(run / CHECKPOINT_NAME, "policy")["step"] \
            < plain.policy.steps:
        raise ValueError(f"the world model trains on the rollouts of the {task} {algo} seed-{seed} cell "
                         f"({run.name}): finish that cell first")
    return checkpoint_student(run, task)


def _world_model(config: SuccessBenchConfig, task: str, data: Path, device: str = "cpu") -> Path:
    path = (Path(config.workdir) / "world_models"
            / f"{task}{_demos_tag(config)}{_demonstrations_tag(config)}{_world_model_tag(config)}.pt")
    _when_free(lambda: train_world_model(TrainWorldModelConfig(
        data=str(data), out=str(path), model=config.world_model, steps=config.world_model_steps, demos=config.demos,
        with_rollouts=config.wm_rollouts > 0,
        validate_every=config.world_model_steps, seed=0, device=device, threads=config.threads,
        progress=config.ray_address is None,
    )), f"{task} world model")  # resumes, or returns at once when the checkpoint is finished
    return path


def evaluation_interval(steps: int, evaluations: int) -> int:
    """The ``eval_every`` that gives exactly ``evaluations`` periodic evaluations in ``steps``
    training steps (every ``eval_every`` steps, and the final step); ValueError where no
    fixed interval does (e.g. 6 in 10 steps)."""
    if not 1 <= evaluations <= steps:
        raise ValueError(f"evaluations must be between 1 and the {steps} training steps, not {evaluations}")
    interval = -(-steps // evaluations)  # ceil: the last multiple falls before the final step
    if (steps - 1) // interval + 1 != evaluations:
        raise ValueError(f"no fixed interval gives {evaluations} evaluations in {steps} steps; "
                         "choose another count or --steps")
    return interval


def _train_config(
    config: SuccessBenchConfig, task: str, algo: str, seed: int, data: Path, world_model: Path | None,
    device: str | None, workers: int, teacher: Path | None = None,
) -> TrainPolicyConfig:
    """The training run of one cell (its periodic evaluations included)."""
    preset = config.policy
    return TrainPolicyConfig.from_preset(
        preset, data=str(data), out=str(Path(config.workdir) / "runs" / _cell_name(config, task, algo, seed)),
        policy=dataclasses.replace(preset.policy, algo=algo),
        world_model=str(world_model) if uses_imagination(algo) else None, teacher=str(teacher) if teacher else None,
        eval_every=evaluation_interval(preset.steps, config.evaluations), eval_episodes=config.eval_episodes,
        eval_layouts=config.eval_layouts, eval_workers=workers, eval_action_draws=config.action_draws, seed=seed,
        threads=config.threads, demos=config.demos,
        device=device or config.device, progress=config.ray_address is None,  # a Ray worker's bars go to a log
    )


def run_cell(
    config: SuccessBenchConfig, task: str, algo: str, seed: int, data: Path, world_model: Path | None,
    device: str | None = None, workers: int | None = None,
) -> Cell:
    """Train one policy (resuming if interrupted) with its periodic evaluations, then the final
    one; ``device`` and ``workers`` default to the config's (a Ray cell passes its own).

    A ``cp`` cell distils the ``edm`` cell of its task and seed: that run is trained first
    when it is not finished yet (or waited for while another process trains it), and the
    ``edm`` cell later finds it done.
    """
    workers = workers or config.workers
    teacher = None
    if algo == "cp":
        teacher_run = _train_config(config, task, "edm", seed, data, None, device, workers)
        _when_free(lambda: train_policy(teacher_run), f"{task} edm teacher, seed {seed}")
        teacher = Path(teacher_run.out)
    started = time.perf_counter()
    train = _train_config(config, task, algo, seed, data, world_model, device, workers, teacher)
    _, history = train_policy(train)
    call_seconds = time.perf_counter() - started
    checkpoint = Path(train.out) / CHECKPOINT_NAME
    payload = load_checkpoint(checkpoint, "policy")
    train_seconds = payload.get("wall_seconds") or call_seconds
    checks = payload.get("reliance") or [None]
    if config.final_episodes:
        final = evaluate_checkpoint(checkpoint, task, config.final_episodes, config.final_seed,
                                    workers=workers, end_on_success=True, progress=train.progress,
                                    acting=Acting(action_draws=config.action_draws),
                                    journal=Path(train.out) / FINAL_JOURNAL)
        wins, episodes, final_seconds = sum(final.successes), final.episodes, final.seconds
    else:
        wins, episodes = round(history[-1].success_rate * history[-1].episodes), history[-1].episodes
        final_seconds = time.perf_counter() - started - call_seconds
    return Cell(task, algo, seed, [point.success_rate for point in history], wins, episodes, train_seconds,
                final_seconds, config.demos, checks[-1])


def _cell_name(config: SuccessBenchConfig, task: str, algo: str, seed: int) -> str:
    """A cell's run and result name; the evaluation count and fresh layouts are in it because
    the paper protocol depends on them, and the policy preset because the result does, so cells
    of 5 and of 15 evaluations, on fixed or fresh layouts, of one budget or another, share a
    workdir (its data and world models) without one being read back as another."""
    fresh = "_fresh" if config.eval_layouts == "fresh" else ""
    world_model = _world_model_tag(config) if uses_imagination(algo) else ""
    draws = f"_draws{config.action_draws}" if config.action_draws > 1 else ""
    return (f"{task}_{algo}_s{seed}_e{config.evaluations}{fresh}{_demos_tag(config)}"
            f"{_demonstrations_tag(config)}{draws}{world_model}{_preset_tag(config.policy)}")


def _world_model_tag(config: SuccessBenchConfig) -> str:
    """What sets the world model apart from the grid's own: the rollouts it also trained on
    (``_wmr<N>n<noise>`` of the noisy expert, ``_wmr<N>p<algo>`` of a policy, ``...s<seed>`` where
    its seed is not 0), no past actions read (``_wmnoact``)."""
    policy_seed = f"s{config.wm_policy_seed}" if config.wm_policy_seed else ""
    source = (f"p{config.wm_policy_rollouts}{policy_seed}" if config.wm_policy_rollouts is not None
              else f"n{config.rollout_noise:g}")
    rollouts = f"_wmr{config.wm_rollouts}{source}" if config.wm_rollouts else ""
    return rollouts + ("" if config.world_model.reads_actions else "_wmnoact")


def _demonstrations_tag(config: SuccessBenchConfig) -> str:
    """Which demonstrations: their DART noise, the Adroit expert when one was chosen, and the
    pool's first seed when it is not 0."""
    pool = f"_pool{config.demo_seed}" if config.demo_seed else ""
    return demonstrations_tag(config.dart_noise, config.expert) + pool


def _demos_tag(config: SuccessBenchConfig) -> str:
    return "" if config.demos == DEFAULT_DEMOS else f"_d{config.demos}"


def _preset_tag(preset: PolicyPreset) -> str:
    """'' for the ``cpu`` preset (the bench's default keeps the short name), ``_<name>`` for
    another named preset, else what differs from the ``cpu`` preset (e.g. ``_steps6000``,
    ``_num_points128``; a digest of it where that runs long), so that a setting added later
    with a default leaves the names of cells already stored as they were."""
    for name, known in POLICY_PRESETS.items():
        if preset == known:
            return "" if name == "cpu" else f"_{name}"
    changes = "_".join(f"{name}{value}" for name, value in _changed_settings(POLICY_PRESETS["cpu"], preset))
    changes = re.sub(r"[^A-Za-z0-9._,-]", "", changes)
    if len(changes) > 48:
        return f"_{preset.steps}steps-{hashlib.sha1(changes.encode()).hexdigest()[:8]}"
    return f"_{changes}"


def _changed_settings(base: Any, other: Any) -> list[tuple[str, Any]]:
    """(leaf field name, value in ``other``) of every nested dataclass field where ``other``
    differs from ``base``, in field order."""
    changed = []
    for setting in dataclasses.fields(base):
        ours, theirs = getattr(base, setting.name), getattr(other, setting.name)
        if dataclasses.is_dataclass(ours) and dataclasses.is_dataclass(theirs):
            changed += _changed_settings(ours, theirs)
        elif ours != theirs:
            changed.append((setting.name, theirs))
    return changed


def cell_path(config: SuccessBenchConfig, task: str, algo: str, seed: int) -> Path:
    cells = Path(config.cells) if config.cells else Path(config.workdir) / "cells"
    return cells / f"{_cell_name(config, task, algo, seed)}.json"


def _describe(cell: Cell) -> str:
    return (f"{cell.task} {cell.algo} seed {cell.seed}: paper {cell.paper:.0%} (evaluations {cell.periodic}), "
            f"final {cell.final_wins}/{cell.final_episodes}, trained in {cell.train_seconds:.0f} s")


def _store(config: SuccessBenchConfig, cell: Cell) -> None:
    path = cell_path(config, cell.task, cell.algo, cell.seed)
    atomic_write_text(path, json.dumps(dataclasses.asdict(cell), indent=1))


def _take_shared(config: SuccessBenchConfig, task: str, algo: str, seed: int) -> Cell | None:
    """The cell from ``config.shared_cells`` (the first directory holding it), stored as this
    grid's own; None for a method that reads a world model, or where none holds it."""
    if uses_imagination(algo):
        return None
    name = cell_path(config, task, algo, seed).name
    source = next((path for directory in config.shared_cells if (path := Path(directory) / name).exists()), None)
    if source is None:
        return None
    cell = read_cell(source)
    _store(config, cell)
    print(f"{name}: taken from {source.parent} (--shared-cells)", flush=True)
    return cell


def take_shared_cells(config: SuccessBenchConfig, grid: list[tuple[str, str, int]]) -> dict[tuple[str, str, int], Cell]:
    """The cells of ``grid`` that this grid has not finished and ``config.shared_cells`` holds, copied
    in as its own (nothing is trained): what a run takes before its first cell, and a report too."""
    return {key: cell for key in grid
            if not cell_path(config, *key).exists() and (cell := _take_shared(config, *key)) is not None}


def _run_locally(config: SuccessBenchConfig, todo: list[tuple[str, str, int]]) -> dict[tuple[str, str, int], Cell]:
    """The unfinished cells one after the other in this process, each claimed first (cells
    another process holds are skipped, those it finished meanwhile read back) and stored as
    it finishes. A task's world model is built by its first cell that reads one, so a process
    whose cell reads none trains it while another process writes the world model."""
    done = {}
    datasets: dict[str, Path] = {}
    world_models: dict[str, Path] = {}
    runs = Path(config.workdir) / "runs"
    for task, algo, seed in todo:
        name = _cell_name(config, task, algo, seed)
        try:
            with exclusive_writer(runs, lock_name=f".{name}.lock"):
                if (path := cell_path(config, task, algo, seed)).exists():
                    done[task, algo, seed] = read_cell(path)
                    continue
                if (shared := _take_shared(config, task, algo, seed)) is not None:  # finished there meanwhile
                    done[task, algo, seed] = shared
                    continue
                if task not in datasets:  # once per task: the collection check opens the data set and an env
                    datasets[task] = _dataset(config, task)
                if uses_imagination(algo) and task not in world_models:
                    world_models[task] = _world_model(config, task, datasets[task])
                print(f"training {algo} on {task}, seed {seed}", flush=True)
                done[task, algo, seed] = cell = run_cell(config, task, algo, seed, datasets[task],
                                                         world_models.get(task))
                _store(config, cell)
                print(_describe(cell), flush=True)
        except DirectoryBusyError:
            print(f"{name}: another process is running it; skipped", flush=True)
    return done


def _run_on_ray(config: SuccessBenchConfig, todo: list[tuple[str, str, int]]) -> dict[tuple[str, str, int], Cell]:
    """The unfinished cells as Ray jobs (world models first, one job per task); each cell is
    stored by the driver as it arrives; cells lost on every retry are reported, not stored."""
    config = dataclasses.replace(config, workdir=str(Path(config.workdir).resolve()))  # the same for every worker
    with ray_cluster(config.ray_address) as ray:
        gpus = 1 if cluster_gpus(ray) else 0
        device = "cuda" if gpus else "cpu"
        tasks = list(dict.fromkeys(task for task, _, _ in todo))
        data = {task: _dataset(config, task) for task in tasks}
        world_models: dict[str, Path | None] = dict.fromkeys(tasks)
        if any(map(uses_imagination, config.algos)):
            jobs = [(config, task, data[task], device) for task in tasks]
            for index, outcome in as_completed(_world_model, jobs, num_cpus=config.threads, num_gpus=gpus):
                if isinstance(outcome, Lost):
                    raise JobsLost(f"{tasks[index]}: the world model's Ray worker died on every attempt "
                                   f"({outcome.reason}); rerun to resume it")
                world_models[tasks[index]] = outcome
        done, lost = {}, []
        jobs = [(config, task, algo, seed, data[task], world_models[task], device, 1) for task, algo, seed in todo]
        with tqdm(total=len(todo), desc="bench cells on Ray", unit="cell") as bar:
            for index, outcome in as_completed(run_cell, jobs, num_cpus=config.threads, num_gpus=gpus, max_retries=1):
                if isinstance(outcome, Lost):
                    lost.append(f"{'/'.join(map(str, todo[index]))} ({outcome.reason})")
                else:
                    done[todo[index]] = outcome
                    _store(config, outcome)
                    bar.write(_describe(outcome))
                bar.update(1)
    if lost:
        print(f"missing cells, their workers died on every attempt (a rerun resumes them): {'; '.join(lost)}")
    return done


def run_grid(config: SuccessBenchConfig, grid: list[tuple[str, str, int]]) -> list[Cell]:
    """The (task, algo, seed) cells of ``grid`` in its order, finished ones read back from disk,
    the others run (locally or on Ray); returns the finished cells in the grid's order."""
    evaluation_interval(config.policy.steps, config.evaluations)  # a count it cannot give fails before any work
    software_render_threads(config.threads)  # before the collections render (a local Ray's workers inherit it)
    finished = {key: read_cell(path) for key in grid if (path := cell_path(config, *key)).exists()}
    finished |= take_shared_cells(config, grid)  # skips the cells finished here
    for cell in finished.values():
        print(_describe(cell), flush=True)
    todo = [key for key in grid if key not in finished]
    if todo and config.ray_address is None:
        finished |= _run_locally(config, todo)
    elif todo:
        finished |= _run_on_ray(config, todo)
    return [finished[key] for key in grid if key in finished]


def run(config: SuccessBenchConfig = PRESETS["cpu"]) -> list[Cell]:
    """Every (task, algo, seed) cell of the config, task by task and in a task seed by seed (the
    variants of one seed side by side first); prints the table of the cells that finished."""
    cells = run_grid(config, [(task, algo, seed) for task in config.tasks for seed in config.seeds
                              for algo in config.algos])
    if not cells:
        return cells
    print()
    print(format_table(cells, config))
    print(f"wrote {plot_success(cells, Path(config.workdir) / 'success.png')}")
    return cells


def format_table(cells: list[Cell], config: SuccessBenchConfig) -> str:
    """Markdown: per task and variant, paper protocol / honest protocol [95 % interval]; the
    last row averages the tasks."""
    summaries = summarize(cells)
    tasks = list(dict.fromkeys(task for task, _ in summaries))
    algos = list(dict.fromkeys(algo for _, algo in summaries))
    lines = [
        f"Success (%), {config.demos} demos per task, seeds {', '.join(map(str, config.seeds))}, "
        f"{config.policy.steps} steps x batch {config.policy.batch_size}, {config.evaluations} evaluation(s) of "
        f"{config.eval_episodes} episodes during training, final checkpoint on "
        f"{config.final_episodes or config.eval_episodes} episodes. Each entry: paper protocol / honest "
        "protocol [95 % Wilson interval]; the paper's Table IV (10 demos) or Table I (Adroit) where it has the figure.",
        "",
        "| task | " + " | ".join(algos) + " | paper MP1 / D2A |",
        "| --- | " + " | ".join("---" for _ in algos) + " | --- |",
    ]
    for task in tasks:
        entries = []
        for algo in algos:
            row = summaries[task, algo]
            entries.append(f"{100 * row.paper:.0f} / {100 * row.honest:.0f} [{100 * row.low:.0f}-{100 * row.high:.0f}]")
        reference = "{} / {}".format(*PAPER_REFERENCE[task]) if task in PAPER_REFERENCE else "-"
        lines.append(f"| {task} | " + " | ".join(entries) + f" | {reference} |")
    averages = []
    for algo in algos:
        rows = [summaries[task, algo] for task in tasks]
        averages.append(f"{100 * statistics.fmean(r.paper for r in rows):.1f} / "
                        f"{100 * statistics.fmean(r.honest for r in rows):.1f}")
    lines.append("| mean | " + " | ".join(averages) + " | |")
    return "\n".join(lines)


def plot_success(cells: list[Cell], path: str | Path) -> Path:
    """Grouped bars per task, one per variant: honest success with its 95 % interval, the
    paper protocol as a marker."""
    bars: dict[str, dict[str, SuccessBar]] = {}
    for (task, algo), row in summarize(cells).items():
        bars.setdefault(algo, {})[task] = SuccessBar(row.honest, row.low, row.high, row.seeds, marker=row.paper)
    return plot_success_bars(bars, path, "final checkpoint (bars, 95 % interval; dots: seeds); "
                                         "paper protocol (triangles)")
