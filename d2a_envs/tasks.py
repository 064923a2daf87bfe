"""The task table: every D2A environment id with its suite, simulator task and difficulty."""

from __future__ import annotations

import difflib
from dataclasses import dataclass

from metaworld.env_dict import ALL_V3_ENVIRONMENTS

from d2a_envs.suites.adroit import ADROIT_ENV_IDS

SUITES = ("metaworld", "adroit")
DIFFICULTIES = ("easy", "medium", "hard", "very_hard")

# Meta-World difficulty split of Seo et al. (2022), as used by DP3 and MP1; the rest are easy.
_METAWORLD_DIFFICULTY = {
    "medium": (
        "basketball", "bin-picking", "box-close", "coffee-pull", "coffee-push", "hammer",
        "peg-insert-side", "push-wall", "soccer", "sweep", "sweep-into",
    ),
    "hard": ("assembly", "hand-insert", "pick-out-of-hole", "pick-place", "push", "push-back"),
    "very_hard": ("shelf-place", "disassemble", "stick-pull", "stick-push", "pick-place-wall"),
}

# The 34 Meta-World tasks of the paper's Table I (as DP3's, MP1's and FlowPolicy's task
# configs hold them): 21 easy, 4 medium, 4 hard, 5 very hard. The Adroit tasks are all in it.
_METAWORLD_TABLE1 = frozenset({
    "button-press", "button-press-wall", "dial-turn", "door-close", "door-open", "door-unlock",
    "drawer-close", "faucet-close", "faucet-open", "handle-press", "handle-pull", "lever-pull",
    "peg-unplug-side", "plate-slide", "plate-slide-back", "plate-slide-back-side", "plate-slide-side",
    "reach", "reach-wall", "window-close", "window-open",
    "coffee-pull", "hammer", "peg-insert-side", "soccer",
    "assembly", "hand-insert", "pick-place", "push",
    "disassemble", "pick-place-wall", "shelf-place", "stick-pull", "stick-push",
})


@dataclass(frozen=True)
class TaskSpec:
    """One registered environment.

    Attributes:
        env_id: Gymnasium id, e.g. ``D2A-MetaWorld-Hammer-v0``.
        suite: ``metaworld`` or ``adroit``.
        task: the simulator's own task name (``hammer-v3``, ``door``).
        name: short kebab-case name used on the command line (``hammer``, ``adroit-door``).
        difficulty: Meta-World difficulty split; ``None`` for Adroit.
        table1: whether the paper's Table I reports the task.
    """

    env_id: str
    suite: str
    task: str
    name: str
    difficulty: str | None
    table1: bool


def _camel(kebab: str) -> str:
    return "".join(part.capitalize() for part in kebab.split("-"))


def _metaworld_specs() -> list[TaskSpec]:
    difficulty_of = {name: level for level, names in _METAWORLD_DIFFICULTY.items() for name in names}
    specs = []
    for task in ALL_V3_ENVIRONMENTS:
        name = task.removesuffix("-v3")
        specs.append(TaskSpec(
            env_id=f"D2A-MetaWorld-{_camel(name)}-v0", suite="metaworld", task=task, name=name,
            difficulty=difficulty_of.get(name, "easy"), table1=name in _METAWORLD_TABLE1,
        ))
    return specs


def _adroit_specs() -> list[TaskSpec]:
    return [
        TaskSpec(
            env_id=f"D2A-Adroit-{_camel(task)}-v0", suite="adroit", task=task, name=f"adroit-{task}", difficulty=None,
            table1=True,
        )
        for task in ADROIT_ENV_IDS
    ]


TASKS: tuple[TaskSpec, ...] = tuple(_metaworld_specs() + _adroit_specs())


def list_tasks(suite: str | None = None, difficulty: str | None = None, table1: bool | None = None) -> list[TaskSpec]:
    """Registered tasks, optionally filtered by suite, (Meta-World) difficulty and whether the
    paper's Table I reports them."""
    if suite is not None and suite not in SUITES:
        raise ValueError(f"unknown suite {suite!r}; choose one of {SUITES}")
    if difficulty is not None and difficulty not in DIFFICULTIES:
        raise ValueError(f"unknown difficulty {difficulty!r}; choose one of {DIFFICULTIES}")
    return [
        spec for spec in TASKS
        if (suite is None or spec.suite == suite) and (difficulty is None or spec.difficulty == difficulty)
        and (table1 is None or spec.table1 == table1)
    ]


def get_task(name_or_id: str) -> TaskSpec:
    """Look a task up by env id (``D2A-MetaWorld-Hammer-v0``), short name (``hammer``,
    ``adroit-door``) or simulator name (``hammer-v3``); unknown names get suggestions."""
    for spec in TASKS:
        if name_or_id in (spec.env_id, spec.name, spec.task if spec.suite == "metaworld" else spec.name):
            return spec
    candidates = [spec.env_id for spec in TASKS] + [spec.name for spec in TASKS]
    close = difflib.get_close_matches(name_or_id, candidates, n=3, cutoff=0.5)
    hint = f"; did you mean {', '.join(close)}?" if close else "; `d2a tasks` lists them all"
    raise ValueError(f"unknown task {name_or_id!r}{hint}")
