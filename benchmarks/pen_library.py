"""Build Pen's sequence library (:mod:`collectors.pen_sequences`) by continuation.

1. A seed: the Pen planner (:mod:`collectors.adroit_experts`) acts in the true model for one
   target and its 200 executed actions are kept.
2. Continuation over the grid of target angles: the unsolved node nearest (in angle) to a
   solved one, or to the seed, starts from that sequence and is optimised for its own target
   by random search on the whole sequence (smooth offsets: knots linearly interpolated over the
   episode, the wrist sampled wider than the fingers; the incumbent stays a candidate), scored
   by how far the best ``hold_steps`` steps of the episode are from the env's success
   (orientation dot product above 0.95, centre within 7.5 cm; a margin asked for both) plus
   ``tracking`` x the mean squared change from the starting sequence, which keeps neighbours
   alike, so that a node's sequence also serves targets near it.
3. A retry: a node whose sequence meets its target on fewer than ``retry_below`` steps is
   optimised again from each other solved neighbour, keeping the best.

Every candidate is scored on the true model (2 ms, 5 physics steps per control step) from the
env's initial state, so a sequence replays in the env exactly as scored. The file is written
after every node: rerunning the command resumes the build.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
from mujoco import rollout
from tqdm import tqdm

from collectors.adroit_experts import EXPERTS, PlannerReplica
from collectors.evaluation import wilson_interval
from collectors.pen_sequences import DEFAULT_LIBRARY, SequenceLibrary, as_stored, target_roll_pitch
from collectors.predictive_sampling import planning_model
from d2a_envs.suites.adroit import PHYSICS_STATE, AdroitEnv, physics_vector, set_physics

SUCCESS_DOT, SUCCESS_DISTANCE = 0.95, 0.075  # the env's success
CHECK_FIRST_LAYOUT = 1000  # apart from the demonstrations' layouts (0, 1, ...)
_TRACKED = ("object_top", "object_bottom", "target_top", "target_bottom", "eps_ball")


@dataclass(frozen=True)
class PenLibraryConfig:
    """Every setting of the build (defaults: the shipped library's).

    Attributes:
        out: the library file (resumed when it exists).
        nodes: grid nodes per angle over [-1, 1] rad.
        steps: actions per sequence (the env's episode length).
        seed_target: (roll, pitch) of the planner's seed episode.
        planner_seed: the seed of its random search.
        iterations, samples: random-search rounds per node and candidates per round.
        knots: knots of the offsets over the episode.
        wrist_sigma, finger_sigma: offset noise of the wrist's and the other actuators' knots.
        tracking: weight of the mean squared change from the starting sequence.
        hold_steps: how many of the episode's best steps the score reads.
        retry_below: nodes meeting their target on fewer steps are retried from other neighbours.
        search_seed: seed of the random search.
        check_layouts: seeded layouts (1000, 1001, ...) on which the finished library is checked,
            its nearest node and its bilinear blend (0: no check).
    """

    out: str = str(DEFAULT_LIBRARY)
    nodes: int = 6
    steps: int = 200
    seed_target: tuple[float, float] = (-0.8, 0.0)
    planner_seed: int = 0
    iterations: int = 20
    samples: int = 32
    knots: int = 11
    wrist_sigma: float = 0.15
    finger_sigma: float = 0.04
    tracking: float = 2.0
    hold_steps: int = 40
    retry_below: int = 10
    search_seed: int = 0
    check_layouts: int = 100

    def __post_init__(self) -> None:
        if self.nodes < 2 or self.steps < 2 or self.knots < 2 or self.samples < 2 or self.iterations < 0:
            raise ValueError(f"need nodes, steps, knots, samples >= 2 and iterations >= 0: {self}")
        if not 1 <= self.hold_steps <= self.steps:
            raise ValueError(f"hold_steps must be in [1, steps], got {self.hold_steps}")


class PenRollouts:
    """The Pen scene on the true model, from the env's initial state: sequences in, success out."""

    def __init__(self) -> None:
        scene = AdroitEnv("pen", state_obs=False, physics_obs=True)
        self.initial = scene.reset(seed=0)[0]["physics"]  # every reset starts here; only the target differs
        make_cost, _ = EXPERTS["pen"]
        self.model = planning_model(mujoco.MjSpec.from_file(scene.model_path), make_cost(scene.model))
        self.data = mujoco.MjData(self.model)
        self.action_mean, self.action_scale = scene.action_map
        self.frame_skip = scene.frame_skip
        scene.close()
        self._target = self.model.body("target").id
        self._columns = [self.model.sensor(f"planning/{name}").adr[0] for name in _TRACKED]
        self._rollout_data = [mujoco.MjData(self.model)]
        self.actuator_names = [self.model.actuator(i).name for i in range(self.model.nu)]

    def set_target(self, roll: float, pitch: float) -> None:
        """Put the target at (roll, pitch) and the scene in its initial state."""
        from gymnasium_robotics.utils.rotations import euler2quat

        self.model.body_quat[self._target] = euler2quat(np.array([roll, pitch, 0.0]))
        state = self.initial[: mujoco.mj_stateSize(self.model, PHYSICS_STATE)]
        set_physics(self.model, self.data, "pen", np.concatenate([state, self.model.body_quat[self._target]]))

    def measure(self, sequences: np.ndarray, roll: float, pitch: float) -> tuple[np.ndarray, np.ndarray]:
        """(orientation dot product, centre distance), each (n, steps), of sequences (n, steps, nu),
        as the env computes them after every control step."""
        self.set_target(roll, pitch)
        state = np.empty(mujoco.mj_stateSize(self.model, PHYSICS_STATE))
        mujoco.mj_getState(self.model, self.data, state, PHYSICS_STATE)
        controls = np.repeat(self.action_mean + np.clip(sequences, -1.0, 1.0) * self.action_scale, self.frame_skip, 1)
        _, sensors = rollout.rollout(self.model, self._rollout_data, state, controls)
        # The env judges a control step by the positions MuJoCo computed during its last physics
        # step (of the state before it), which that step's sensors hold.
        frames = sensors[:, np.arange(1, sequences.shape[1] + 1) * self.frame_skip - 1]
        top, bottom, target_top, target_bottom, ball = (frames[..., c : c + 3] for c in self._columns)
        centre = (top + bottom) / 2  # the pen body's origin, where the env measures its distance

        def unit(v: np.ndarray) -> np.ndarray:
            return v / np.linalg.norm(v, axis=-1, keepdims=True)

        dot = (unit(top - bottom) * unit(target_top - target_bottom)).sum(-1)
        return dot, np.linalg.norm(centre - ball, axis=-1)


def success_steps(dot: np.ndarray, distance: np.ndarray) -> np.ndarray:
    """Steps (per sequence) at which the env counts success."""
    return ((dot > SUCCESS_DOT) & (distance < SUCCESS_DISTANCE)).sum(-1)


def hold_score(dot: np.ndarray, distance: np.ndarray, hold_steps: int) -> np.ndarray:
    """Mean shortfall from success, with a margin, over each sequence's best ``hold_steps`` steps."""
    shortfall = np.clip(0.98 - dot, 0.0, None) + np.clip(distance - 0.05, 0.0, None)
    return np.sort(shortfall, axis=1)[:, :hold_steps].mean(1)


def optimise(rollouts: PenRollouts, start: np.ndarray, roll: float, pitch: float, config: PenLibraryConfig,
             rng: np.random.Generator) -> np.ndarray:
    """``start`` improved for the target (roll, pitch): greedy random search over smooth offsets."""
    steps = np.arange(config.steps)
    knot_times = np.linspace(0, config.steps - 1, config.knots)
    spread = np.stack([np.interp(steps, knot_times, row) for row in np.eye(config.knots)], axis=1)  # (T, K)
    sigma = np.array([config.wrist_sigma if name.startswith("A_WRJ") else config.finger_sigma
                      for name in rollouts.actuator_names])
    best = as_stored(start)
    for _ in range(config.iterations):
        noise = rng.normal(0.0, 1.0, (config.samples, config.knots, len(sigma))) * sigma
        noise[0] = 0.0  # the incumbent stays a candidate
        candidates = as_stored(np.clip(best[None] + np.einsum("tk,nku->ntu", spread, noise), -1.0, 1.0))
        score = hold_score(*rollouts.measure(candidates, roll, pitch), config.hold_steps)
        score += config.tracking * ((candidates - start[None]) ** 2).mean((1, 2))
        best = candidates[int(np.argmin(score))]
    return best


def seed_sequence(rollouts: PenRollouts, config: PenLibraryConfig) -> np.ndarray:
    """The planner's executed actions for ``seed_target``, played in the true model."""
    planner = PlannerReplica("pen")
    rollouts.set_target(*config.seed_target)
    data, actions = rollouts.data, []
    for step in tqdm(range(config.steps), desc="pen seed (planner)"):
        action = planner.act(physics_vector(rollouts.model, data, "pen"), step, config.planner_seed)
        data.ctrl[:] = rollouts.action_mean + action * rollouts.action_scale
        mujoco.mj_step(rollouts.model, data, rollouts.frame_skip)
        actions.append(action)
    return np.stack(actions)


def build(config: PenLibraryConfig) -> SequenceLibrary:
    """Build (or resume) the library at ``config.out``; prints each node and the time taken."""
    rollouts = PenRollouts()
    out = Path(config.out)
    library = SequenceLibrary.load(out) if out.exists() else \
        SequenceLibrary.empty(config.nodes, config.steps, len(rollouts.actuator_names))
    if library.sequences.shape[:3] != (config.nodes, config.nodes, config.steps):
        raise ValueError(f"{out} holds a {library.sequences.shape[:3]} library, not ({config.nodes}, {config.nodes}, "
                         f"{config.steps}): choose another --out")
    rng = np.random.default_rng(config.search_seed + int(library.attempts.sum()))
    axis, started = library.axis, time.perf_counter()

    def solve(node: tuple[int, int], start: np.ndarray) -> None:
        roll, pitch = axis[node[0]], axis[node[1]]
        candidate = optimise(rollouts, start, roll, pitch, config, rng)
        held = int(success_steps(*rollouts.measure(candidate[None], roll, pitch))[0])
        if held > library.hold_steps[node]:
            library.sequences[node], library.hold_steps[node] = candidate, held
        library.attempts[node] += 1
        library.save(out)
        tqdm.write(f"node roll {roll:+.2f} pitch {pitch:+.2f}: meets its target on {library.hold_steps[node]} steps "
                   f"(attempt {library.attempts[node]})")

    unsolved = [(i, j) for i in range(config.nodes) for j in range(config.nodes) if not library.solved[i, j]]
    seed = seed_sequence(rollouts, config) if unsolved and not library.solved.any() else None
    for _ in tqdm(range(len(unsolved)), desc="pen library"):
        sources = [(np.array([axis[i], axis[j]]), library.sequences[i, j]) for i, j in np.argwhere(library.solved)]
        if seed is not None:
            sources.append((np.array(config.seed_target), seed))
        node, start = min(((n, s) for n in unsolved for s in sources),
                          key=lambda pair: np.linalg.norm(axis[list(pair[0])] - pair[1][0]))
        unsolved.remove(node)
        solve(node, start[1])
    weak = [tuple(n) for n in np.argwhere((library.hold_steps < config.retry_below) & (library.attempts == 1))]
    for i, j in tqdm(weak, desc="pen retries"):
        for a, b in ((i - 1, j), (i + 1, j), (i, j - 1), (i, j + 1)):
            if 0 <= a < config.nodes and 0 <= b < config.nodes and library.hold_steps[a, b] >= config.retry_below:
                solve((i, j), library.sequences[a, b])
        library.attempts[i, j] = max(library.attempts[i, j], 2)  # retried, even with no strong neighbour
        library.save(out)
    print(f"{int(library.solved.sum())} nodes solved, {int((library.hold_steps > 0).sum())} meet their target; "
          f"this call took {time.perf_counter() - started:.0f} s")
    if not config.check_layouts:
        return library
    layouts = range(CHECK_FIRST_LAYOUT, CHECK_FIRST_LAYOUT + config.check_layouts)
    for blend, name in ((False, "the nearest node"), (True, "the bilinear blend")):
        wins = check(library, rollouts, layouts, blend)
        low, high = wilson_interval(wins, config.check_layouts)
        print(f"{name} meets the target in {wins}/{config.check_layouts} seeded layouts "
              f"[{100 * low:.1f}-{100 * high:.1f}] (layouts {CHECK_FIRST_LAYOUT}-, on the true model)")
    return library


def check(library: SequenceLibrary, rollouts: PenRollouts, layouts: range, blend: bool = False) -> int:
    """In how many of the env's seeded ``layouts`` the library (its nearest node, or with
    ``blend`` its bilinear blend) meets the target."""
    env = AdroitEnv("pen", state_obs=False)
    wins = 0
    for layout in layouts:
        env.reset(seed=layout)
        roll, pitch = target_roll_pitch(env.model.body_quat[env.model.body("target").id])
        sequence = library.sequence(roll, pitch, blend)
        wins += int(success_steps(*rollouts.measure(sequence[None], roll, pitch))[0] > 0)
    env.close()
    return wins
