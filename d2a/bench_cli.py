"""The ``d2a bench`` subcommands: each runs a script of ``benchmarks/`` that prints its figures."""

from __future__ import annotations

import argparse
import dataclasses
from typing import TYPE_CHECKING, Any

from d2a.cli_options import (
    ALGOS,
    EXPERT_KINDS,
    NON_NEGATIVE,
    NON_NEGATIVE_FLOAT,
    POSITIVE,
    STATE_ALGOS,
    add_eval_layouts_option,
    add_policy_options,
    add_ray_option,
    parse_box,
    replace_given,
    with_policy_options,
)

if TYPE_CHECKING:
    from d2a_agents.world_model.triplane import WorldModelConfig


def add_grid_options(parser: argparse.ArgumentParser, results: str, workdir: str) -> None:
    """The options every grid bench (table1, table4) shares."""
    parser.add_argument("--seed", type=NON_NEGATIVE, action="append", default=None, help="default: 0 1 2")
    parser.add_argument("--steps", type=POSITIVE, default=None, help="policy training steps (default: preset's)")
    add_policy_options(parser)
    parser.add_argument("--evaluations", type=POSITIVE, default=None, help="periodic evaluations (default 5)")
    add_eval_layouts_option(parser)
    parser.add_argument("--workers", type=POSITIVE, default=None, help="evaluation worker processes")
    parser.add_argument("--workdir", default=None, help=f"data, world models, checkpoints (default {workdir})")
    parser.add_argument("--results", default=None,
                        help=f"finished cells and the report (default {results}); a rerun skips its cells")
    parser.add_argument("--shared-cells", action="append", default=None, metavar="DIR",
                        help="another grid's cells made from the same demonstrations and settings (Table I's are "
                             "the first 10 of Table IV's): its cells of methods without a world model are copied, "
                             "not rerun (repeatable)")
    parser.add_argument("--threads", type=POSITIVE, default=None, help="torch threads per cell (default 1)")
    parser.add_argument("--report", action="store_true", help="only write the report of the finished cells "
                                                              "(those of --shared-cells copied in; nothing is trained)")
    add_demo_seed_option(parser)
    add_world_model_data_options(parser)
    add_ray_option(parser)


def add_demo_seed_option(parser: argparse.ArgumentParser) -> None:
    """Which set of demonstrations the cells train on: the pool collected from this env seed on."""
    parser.add_argument("--demo-seed", type=NON_NEGATIVE, default=None, metavar="SEED",
                        help="collect the demonstrations from this env seed on (default 0): another seed, another "
                             "set (e.g. 1000), with its own data, world models and cells (_pool<SEED>)")


def add_world_model_data_options(parser: argparse.ArgumentParser) -> None:
    """What the world model trains on beyond the cell's demonstrations (the policy never sees it),
    and whether it reads past actions; the imagining cells, their data and world models are
    named apart, the others are shared."""
    parser.add_argument("--wm-rollouts", type=NON_NEGATIVE, default=None,
                        help="noisy expert rollouts per task the world model also trains on (default 0)")
    parser.add_argument("--rollout-noise", type=NON_NEGATIVE_FLOAT, default=None,
                        help="std of their action noise (default 0.3)")
    parser.add_argument("--wm-policy-rollouts", default=None, metavar="ALGO",
                        help="those rollouts are the policy's of this bench's own ALGO cell of seed "
                             "--wm-policy-seed (finished first, with the plain world model), not the noisy expert's")
    parser.add_argument("--wm-policy-seed", type=NON_NEGATIVE, default=None, metavar="SEED",
                        help="the seed of that ALGO cell (default 0)")
    parser.add_argument("--wm-without-actions", action="store_true",
                        help="the world model reads no past actions: it imagines from the scene alone")


def add_cell_reading_options(parser: argparse.ArgumentParser) -> None:
    """The options of the reports that read finished cells: where they are, which tasks, a page to write."""
    parser.add_argument("--results", action="append", required=True,
                        help="a directory of cells, or a grid's results holding cells/ (repeatable)")
    parser.add_argument("--task", action="append", default=None,
                        help="only this task's cells, as cell names spell it (adroit-door); repeatable")
    parser.add_argument("--markdown", default=None, help="also write the report to this file (default: none)")


def cmd_bench_envs(args: argparse.Namespace) -> None:
    from benchmarks.envs import EnvBenchConfig, render_thread_comparison, run

    config = replace_given(EnvBenchConfig(), task=args.task, steps=args.steps, seed=args.seed,
                           render_rounds=args.render_rounds)
    (render_thread_comparison if args.render_threads else run)(config)


def cmd_bench_experts(args: argparse.Namespace) -> None:
    from benchmarks.experts import ExpertBenchConfig, run

    base = ExpertBenchConfig()
    run(replace_given(base, tasks=tuple(args.task) if args.task else None, episodes=args.episodes,
                       workers=args.workers, ray_address=args.ray, **imitation_fields(args)))


def cmd_bench_dagger(args: argparse.Namespace) -> None:
    from benchmarks.dagger import DaggerConfig, run

    base = DaggerConfig()
    check = replace_given(base.check, tasks=tuple(args.task) if args.task else None, workers=args.workers,
                          **imitation_fields(args))
    run(replace_given(base, check=check, rounds=args.rounds, episodes_per_round=args.episodes_per_round))


def cmd_bench_tune_expert(args: argparse.Namespace) -> None:
    from benchmarks.tune_expert import TuneConfig, run

    run(replace_given(TuneConfig(), task=args.task, iterations=args.iterations, episodes=args.episodes,
                       first_seed=args.first_seed, seed=args.seed, noise=args.noise, out=args.out))


def cmd_bench_pen_library(args: argparse.Namespace) -> None:
    from benchmarks.pen_library import PenLibraryConfig, build

    build(replace_given(PenLibraryConfig(), out=args.out, nodes=args.nodes, iterations=args.iterations,
                        samples=args.samples, tracking=args.tracking, search_seed=args.seed))


def cmd_bench_latency(args: argparse.Namespace) -> None:
    from benchmarks.latency import LatencyBenchConfig, run

    run(replace_given(LatencyBenchConfig(), task=args.task, num_points=args.num_points, repeats=args.repeats,
                       world_model=args.world_model, data=args.data))


def cmd_bench_eval(args: argparse.Namespace) -> None:
    from benchmarks.evaluation_speed import EvaluationSpeedConfig, run

    run(replace_given(EvaluationSpeedConfig(policy=args.policy, task=args.task), episodes=args.episodes,
                      rounds=args.rounds, seed=args.seed, threads=args.threads))


def cmd_bench_train(args: argparse.Namespace) -> None:
    from benchmarks.train import TrainBenchConfig, run

    run(replace_given(TrainBenchConfig(), steps=args.steps, threads=args.threads, device=args.device))


def cmd_bench_ablate(args: argparse.Namespace) -> None:
    from benchmarks.ablation import AblationConfig, run, table

    if args.table:
        print(table(args.workdir or AblationConfig.workdir))
        return
    if not (args.data and args.task):
        raise ValueError("bench ablate needs --data and --task (or --table)")
    run(replace_given(AblationConfig(data=args.data, task=args.task), change=args.change, algo=args.algo,
                       seed=args.seed, world_model=args.world_model, episodes=args.episodes, workdir=args.workdir))


def cmd_bench_wm(args: argparse.Namespace) -> None:
    from benchmarks.world_model import BENCH_MODELS, BenchModel, WorldModelBenchConfig, run

    main, baseline = BENCH_MODELS
    model = replace_given(main.model, plane_pooling=args.plane_pooling, encoder=args.encoder,
                           feature_mode=args.mode, resolution=tuple(args.resolution) if args.resolution else None)
    label = f"{'x'.join(map(str, model.resolution))} {model.encoder}" + (
        "" if model.feature_mode == "triplane" else f" {model.feature_mode}")
    models = (BenchModel(label, model, args.steps or main.steps),)
    if args.baseline_steps != 0:
        models += (dataclasses.replace(baseline, steps=args.baseline_steps or baseline.steps),)
    base = WorldModelBenchConfig()
    env_kwargs = {**base.env_kwargs, **{key: value for key, value in (
        ("num_points", args.num_points), ("image_size", args.image_size), ("backend", args.backend)) if value}}
    run(replace_given(base, tasks=tuple(args.task) if args.task else None, models=models, env_kwargs=env_kwargs,
                       horizons=tuple(args.horizon) if args.horizon else None, workdir=args.workdir))


def cmd_bench_fusion(args: argparse.Namespace) -> None:
    from benchmarks.fusion import FusionBenchConfig, run

    run(replace_given(FusionBenchConfig(), repeats=args.repeats))


def cmd_bench_points(args: argparse.Namespace) -> None:
    from benchmarks.point_budget import PointBudgetConfig, run

    run(replace_given(PointBudgetConfig(), tasks=tuple(args.task) if args.task else None, points=args.points,
                      layouts=args.layouts, backend=args.backend, crop_box=args.crop_box))


def cmd_bench_change(args: argparse.Namespace) -> None:
    from benchmarks.change import ChangeBenchConfig, run

    run(replace_given(ChangeBenchConfig(world_model=args.world_model, data=args.data), demos=args.demos,
                       stride=args.stride, num_points=args.points))


def cmd_bench_wm_fit(args: argparse.Namespace) -> None:
    from benchmarks.world_model_fit import WorldModelFitConfig, run

    run(replace_given(WorldModelFitConfig(world_model=args.world_model, data=args.data, demos=args.demos),
                       stride=args.stride))


def cmd_bench_policy_fit(args: argparse.Namespace) -> None:
    from benchmarks.policy_fit import PolicyFitConfig, run

    run(replace_given(PolicyFitConfig(policies=tuple(args.policy)), data=args.data, demos=args.demos,
                       windows=args.windows, past_actions=args.past_actions))


def cmd_bench_success(args: argparse.Namespace) -> None:
    from benchmarks.success import PRESETS, run

    base = with_policy_options(PRESETS[args.preset], args)
    env_kwargs = {k: v for k, v in dict(image_size=args.image_size, num_points=args.num_points,
                                        backend=args.backend).items() if v is not None}
    world_model = None
    if args.world_model is not None:
        from d2a_agents.world_model.triplane import CPU_PRESET, WorldModelConfig

        # cpu: d2a train-wm's cpu preset (128x128x32, point-scatter); demo: the demo's 32x32x8 Conv3d
        world_model = CPU_PRESET if args.world_model == "cpu" else WorldModelConfig(resolution=(32, 32, 8))
    world_model = world_model_asked(args, world_model, base.world_model)
    run(replace_given(
        base, tasks=tuple(args.task) if args.task else None,
        algos=tuple(args.algo) if args.algo else None, seeds=tuple(args.seed) if args.seed else None,
        workdir=args.workdir, workers=args.workers, env_kwargs=env_kwargs or None, world_model=world_model,
        world_model_steps=args.wm_steps, threads=args.threads, ray_address=args.ray, evaluations=args.evaluations,
        eval_layouts=args.eval_layouts, demos=args.demos, pool=args.pool, cells=args.cells,
        wm_rollouts=args.wm_rollouts, rollout_noise=args.rollout_noise, dart_noise=args.dart_noise,
        wm_policy_rollouts=args.wm_policy_rollouts, wm_policy_seed=args.wm_policy_seed,
        action_draws=args.action_draws, rgb_image_size=args.rgb_image_size, expert=args.expert,
        demo_seed=args.demo_seed,
    ))


def grid_cells(base: Any, args: argparse.Namespace) -> Any:
    """A grid bench's per-cell settings (``SuccessBenchConfig``) with the options given."""
    return replace_given(with_policy_options(base, args), workdir=args.workdir, threads=args.threads,
                          ray_address=args.ray, evaluations=args.evaluations, eval_layouts=args.eval_layouts,
                          workers=args.workers, shared_cells=tuple(args.shared_cells) if args.shared_cells else None,
                          wm_rollouts=args.wm_rollouts, rollout_noise=args.rollout_noise,
                          wm_policy_rollouts=args.wm_policy_rollouts, wm_policy_seed=args.wm_policy_seed,
                          demo_seed=args.demo_seed, world_model=world_model_asked(args, None, base.world_model))


def world_model_asked(args: argparse.Namespace, chosen: WorldModelConfig | None,
                      default: WorldModelConfig) -> WorldModelConfig | None:
    """The world model settings the options ask for: ``chosen`` (None: the preset's), or with
    ``--wm-without-actions`` ``chosen`` or else ``default`` imagining from no past actions."""
    if not args.wm_without_actions:
        return chosen
    return dataclasses.replace(chosen or default, reads_actions=False)


def cmd_bench_table1(args: argparse.Namespace) -> None:
    from benchmarks.table1 import Table1Config, run

    base = Table1Config()
    run(replace_given(base, groups=tuple(args.group) if args.group else None,
                       algos=tuple(args.algo) if args.algo else None, seeds=tuple(args.seed) if args.seed else None,
                       results=args.results, bench=grid_cells(base.bench, args)), report_only=args.report)


def cmd_bench_table4(args: argparse.Namespace) -> None:
    from benchmarks.table4 import Table4Config, run

    base = Table4Config()
    run(replace_given(base, tasks=tuple(args.task) if args.task else None,
                       demos=tuple(args.demos) if args.demos else None,
                       algos=tuple(args.algo) if args.algo else None, seeds=tuple(args.seed) if args.seed else None,
                       results=args.results, bench=grid_cells(base.bench, args)), report_only=args.report)


def cmd_bench_paired(args: argparse.Namespace) -> None:
    from benchmarks.paired import PairedConfig, run

    run(replace_given(PairedConfig(results=tuple(args.results)), algo=args.algo, control=args.control,
                       reference=args.reference, plot=args.plot, markdown=args.markdown,
                       tasks=tuple(args.task) if args.task else None, demos=tuple(args.demos) if args.demos else None,
                       runs=tuple(args.runs) if args.runs else None))


def cmd_bench_order(args: argparse.Namespace) -> None:
    from benchmarks.ordering import OrderingConfig, run

    run(OrderingConfig(results=tuple(args.results), order=tuple(args.order),
                       tasks=tuple(args.task) if args.task else (), markdown=args.markdown, plot=args.plot))


def cmd_bench_ray(args: argparse.Namespace) -> None:
    from benchmarks.ray_scaling import RayScalingConfig, run

    base = RayScalingConfig()
    run(replace_given(base, task=args.task, algo=args.algo, seeds=tuple(args.seed) if args.seed else None,
                       cpus=tuple(args.cpus) if args.cpus else None, workdir=args.workdir,
                       policy=replace_given(base.policy, steps=args.steps)))


def add_imitation_options(parser: argparse.ArgumentParser) -> None:
    """The learnability check's options (``bench experts``, ``bench dagger``)."""
    parser.add_argument("--imitation-demos", type=NON_NEGATIVE, default=None,
                        help="the learnability check: mp1-state trained on this many demonstrations (0: off)")
    parser.add_argument("--imitation-algo", choices=STATE_ALGOS, default=None,
                        help="the check's state policy (default mp1-state; dp3-state: the diffusion expert)")
    parser.add_argument("--imitation-episodes", type=POSITIVE, default=None,
                        help="its evaluation episodes on new layouts (default 100)")
    parser.add_argument("--imitation-dart-noise", type=NON_NEGATIVE_FLOAT, default=None, metavar="STD",
                        help="collect the check's demonstrations with DART noise (d2a collect --dart-noise)")
    parser.add_argument("--imitation-action-draws", type=POSITIVE, default=None, metavar="K",
                        help="its policy acts on the mean of K chunks per plan (d2a eval --action-draws)")
    parser.add_argument("--workdir", default=None, help="the check's data and policies")
    parser.add_argument("--expert", choices=EXPERT_KINDS, default=None,
                        help="the Adroit expert (default: each task's own; Meta-World tasks keep theirs)")


def imitation_fields(args: argparse.Namespace) -> dict[str, Any]:
    """The learnability check's settings given on the command line (``add_imitation_options``)."""
    return dict(imitation_demos=args.imitation_demos, imitation_episodes=args.imitation_episodes,
                workdir=args.workdir, imitation_dart_noise=args.imitation_dart_noise,
                imitation_action_draws=args.imitation_action_draws, imitation_algo=args.imitation_algo,
                expert=args.expert)


def add_bench_commands(commands: Any) -> None:
    """Add ``bench`` and its subcommands to the ``d2a`` command's subparsers."""
    bench = commands.add_parser("bench", help="benchmarks (print figures)").add_subparsers(dest="what", required=True)
    bench_envs = bench.add_parser("envs", help="env steps/s per depth backend")
    bench_envs.add_argument("--task", default=None)
    bench_envs.add_argument("--steps", type=POSITIVE, default=None)
    bench_envs.add_argument("--seed", type=NON_NEGATIVE, default=None)
    bench_envs.add_argument("--render-threads", action="store_true",
                            help="only compare the software renderer's thread pool with drawing in the calling "
                                 "thread (LP_NUM_THREADS unset / 0) at the grids' 256 px and 4096 points")
    bench_envs.add_argument("--render-rounds", type=POSITIVE, default=None,
                            help="with --render-threads: alternating runs of each setting (default 6)")
    bench_envs.set_defaults(func=cmd_bench_envs)

    bench_experts = bench.add_parser("experts", help="expert success per task (Meta-World, Adroit), parallel speed-up")
    bench_experts.add_argument("--task", action="append", default=None, help="default: all 50 Meta-World tasks")
    bench_experts.add_argument("--episodes", type=POSITIVE, default=None)
    bench_experts.add_argument("--workers", type=POSITIVE, default=None)
    add_imitation_options(bench_experts)
    add_ray_option(bench_experts)
    bench_experts.set_defaults(func=cmd_bench_experts)

    bench_dagger = bench.add_parser("dagger", help="DAgger from the learnability check: the state policy acts, the "
                                                   "expert labels, a new policy per round")
    bench_dagger.add_argument("--task", action="append", default=None, help="default adroit-door")
    bench_dagger.add_argument("--rounds", type=NON_NEGATIVE, default=None, help="rounds after the first policy "
                                                                                "(default 3)")
    bench_dagger.add_argument("--episodes-per-round", type=POSITIVE, default=None,
                              help="the policy's labelled episodes added per round (default 10)")
    bench_dagger.add_argument("--workers", type=POSITIVE, default=None, help="evaluation workers (default 1)")
    add_imitation_options(bench_dagger)
    bench_dagger.set_defaults(func=cmd_bench_dagger)

    bench_tune = bench.add_parser("tune-expert", help="hill-climb an Adroit controller's settings on seeded "
                                                      "episodes (success, then speed)")
    bench_tune.add_argument("--task", default=None, help="default adroit-door")
    bench_tune.add_argument("--iterations", type=NON_NEGATIVE, default=None, help="candidates tried (default 60)")
    bench_tune.add_argument("--episodes", type=POSITIVE, default=None, help="tuning episodes per candidate (default 8)")
    bench_tune.add_argument("--first-seed", type=NON_NEGATIVE, default=None, help="first tuning layout (default 1000)")
    bench_tune.add_argument("--seed", type=NON_NEGATIVE, default=None, help="seed of the perturbations")
    bench_tune.add_argument("--noise", type=NON_NEGATIVE_FLOAT, default=None, metavar="STD",
                            help="tune for noise tolerance: Gaussian noise of this std on every executed action "
                                 "(the DART noise of the demonstrations to come), the same draws for every candidate")
    bench_tune.add_argument("--out", default=None, help="JSON of the accepted candidates")
    bench_tune.set_defaults(func=cmd_bench_tune_expert)

    bench_pen = bench.add_parser("pen-library", help="build (or resume) Adroit Pen's sequence library by "
                                                     "continuation over the target's roll and pitch")
    bench_pen.add_argument("--out", default=None, help="the library file (default: the one the package ships)")
    bench_pen.add_argument("--nodes", type=POSITIVE, default=None, help="grid nodes per angle (default 6)")
    bench_pen.add_argument("--iterations", type=NON_NEGATIVE, default=None,
                           help="random-search rounds per node (default 20)")
    bench_pen.add_argument("--samples", type=POSITIVE, default=None, help="candidates per round (default 32)")
    bench_pen.add_argument("--tracking", type=NON_NEGATIVE_FLOAT, default=None,
                           help="weight of the change from the neighbour's sequence (default 2.0)")
    bench_pen.add_argument("--seed", type=NON_NEGATIVE, default=None, help="seed of the random search")
    bench_pen.set_defaults(func=cmd_bench_pen_library)

    bench_latency = bench.add_parser("latency", help="batch-1 CPU latency: MeanFlow 1 NFE vs DDIM 10 NFE, imagination")
    bench_latency.add_argument("--task", default=None)
    bench_latency.add_argument("--num-points", type=POSITIVE, default=None)
    bench_latency.add_argument("--repeats", type=POSITIVE, default=None)
    bench_latency.add_argument("--world-model", help="also time this trained world model (needs --data)")
    bench_latency.add_argument("--data", help="demonstrations to imagine from, with their recorded actions")
    bench_latency.set_defaults(func=cmd_bench_latency)

    bench_eval = bench.add_parser("eval", help="a checkpoint's evaluation with every step's clouds made and with "
                                               "only the steps its policy reads: ms per step, the same episodes")
    bench_eval.add_argument("--policy", required=True, help="policy.pt of d2a train-policy, or its run directory")
    bench_eval.add_argument("--task", required=True)
    bench_eval.add_argument("--episodes", type=POSITIVE, default=None, help="per setting and round (default 5)")
    bench_eval.add_argument("--rounds", type=POSITIVE, default=None, help="alternating rounds (default 2)")
    bench_eval.add_argument("--seed", type=NON_NEGATIVE, default=None, help="first layout (default 100000)")
    bench_eval.add_argument("--threads", type=POSITIVE, default=None, help="torch threads (default 1)")
    bench_eval.set_defaults(func=cmd_bench_eval)

    bench_train = bench.add_parser("train", help="policy training throughput (samples/s) per preset and variant")
    bench_train.add_argument("--steps", type=POSITIVE, default=None, help="timed steps per row (default 30)")
    bench_train.add_argument("--threads", type=POSITIVE, default=None, help="torch threads (default 1)")
    bench_train.add_argument("--device", default=None, help="cpu or cuda")
    bench_train.set_defaults(func=cmd_bench_train)

    bench_ablate = bench.add_parser("ablate", help="one change to the cpu policy preset: train, perception check, "
                                                   "100-episode evaluation; --table sums the runs up")
    bench_ablate.add_argument("--data", default=None, help="data set directory (d2a collect)")
    bench_ablate.add_argument("--task", default=None)
    bench_ablate.add_argument("--change", default=None, help="see benchmarks/ablation.py CHANGES (default none)")
    bench_ablate.add_argument("--algo", choices=ALGOS, default=None)
    bench_ablate.add_argument("--world-model", default=None, help="for the imagination variants")
    bench_ablate.add_argument("--seed", type=NON_NEGATIVE, default=None)
    bench_ablate.add_argument("--episodes", type=POSITIVE, default=None)
    bench_ablate.add_argument("--workdir", default=None)
    bench_ablate.add_argument("--table", action="store_true", help="print the table of the finished runs")
    bench_ablate.set_defaults(func=cmd_bench_ablate)

    bench_wm = bench.add_parser("wm", help="world model IoU vs ablations and persistence (Table II)")
    bench_wm.add_argument("--task", action="append", default=None, help="default: hammer assembly push basketball")
    bench_wm.add_argument("--horizon", type=POSITIVE, action="append", default=None, help="H; repeat (default 4)")
    bench_wm.add_argument("--steps", type=POSITIVE, default=None, help="the main model's steps (default 1500)")
    bench_wm.add_argument("--baseline-steps", type=NON_NEGATIVE, default=None,
                          help="steps of the 32x32x8 volume-conv row (default 300; 0: leave it out)")
    bench_wm.add_argument("--resolution", type=POSITIVE, nargs=3, default=None, metavar=("X", "Y", "Z"),
                          help="the main model's grid (default 128 128 32)")
    bench_wm.add_argument("--encoder", choices=("point-scatter", "volume-conv"), default=None,
                          help="the main model's encoder (default point-scatter)")
    bench_wm.add_argument("--mode", choices=("triplane", "xy", "volume"), default=None,
                          help="the main model's features (default triplane; volume needs --encoder volume-conv)")
    bench_wm.add_argument("--plane-pooling", choices=("mean", "max"), default=None)
    bench_wm.add_argument("--num-points", type=POSITIVE, default=None, help="points per collected cloud (default 4096)")
    bench_wm.add_argument("--image-size", type=POSITIVE, default=None, help="depth image size (default 256)")
    bench_wm.add_argument("--backend", choices=("raycast", "render"), default=None, help="depth backend")
    bench_wm.add_argument("--workdir", default=None)
    bench_wm.set_defaults(func=cmd_bench_wm)

    bench_points = bench.add_parser("points", help="where a task's point budget goes: the object's points among the "
                                                   "N a policy reads, and a flat surface that takes the rest")
    bench_points.add_argument("--task", action="append", default=None,
                              help="repeatable; default: the Meta-World tasks of Table I")
    bench_points.add_argument("--points", type=POSITIVE, default=None, help="points the policy reads (default 128)")
    bench_points.add_argument("--layouts", type=POSITIVE, default=None, help="new layouts per task (default 5)")
    bench_points.add_argument("--backend", choices=("raycast", "render"), default=None,
                              help="depth backend (default render, as the grids)")
    bench_points.add_argument("--crop-box", type=parse_box, default=None,
                              help="x0,y0,z0,x1,y1,z1 in metres (default: each task's own box)")
    bench_points.set_defaults(func=cmd_bench_points)

    bench_fusion = bench.add_parser("fusion", help="two 640x480 depth frames fused to 1024 points: ms on one thread")
    bench_fusion.add_argument("--repeats", type=POSITIVE, default=None)
    bench_fusion.set_defaults(func=cmd_bench_fusion)

    bench_change = bench.add_parser("change", help="how close the imagined change, the observed change and the "
                                                   "present cloud come to where the scene will change")
    bench_change.add_argument("--world-model", required=True, help="checkpoint of d2a train-wm")
    bench_change.add_argument("--data", required=True,
                              help="its demonstrations, or a policy's rollouts (d2a collect --policy; with --demos 0)")
    bench_change.add_argument("--demos", type=NON_NEGATIVE, default=None,
                              help="the world model trained on the first N of each task: measure on the rest; 0: "
                                   "on every episode (default: its own held-out episodes)")
    bench_change.add_argument("--stride", type=POSITIVE, default=None, help="every k-th transition (default 2)")
    bench_change.add_argument("--points", type=POSITIVE, default=None, help="points per cloud (default 64)")
    bench_change.set_defaults(func=cmd_bench_change)

    bench_wm_fit = bench.add_parser("wm-fit", help="a world model on the demonstrations it trained on against new "
                                                   "ones: is what a d2a policy trains on in-sample?")
    bench_wm_fit.add_argument("--world-model", required=True, help="checkpoint of d2a train-wm")
    bench_wm_fit.add_argument("--data", required=True, help="its demonstrations and more of the same task")
    bench_wm_fit.add_argument("--demos", type=POSITIVE, required=True,
                              help="the world model trained on the first N of each task")
    bench_wm_fit.add_argument("--stride", type=POSITIVE, default=None, help="every k-th transition (default 5)")
    bench_wm_fit.set_defaults(func=cmd_bench_wm_fit)

    bench_policy_fit = bench.add_parser("policy-fit", help="a policy's one-step error on the demonstrations it "
                                                           "trained on and on unseen ones, with its reliance")
    bench_policy_fit.add_argument("--policy", action="append", required=True,
                                  help="a checkpoint or run directory (repeatable)")
    bench_policy_fit.add_argument("--data", default=None, help="default: the data set each policy trained on")
    bench_policy_fit.add_argument("--demos", type=POSITIVE, default=None,
                                  help="the policies trained on the first N of each task (default: each one's own)")
    bench_policy_fit.add_argument("--windows", type=POSITIVE, default=None,
                                  help="windows per split, at most (default 512)")
    bench_policy_fit.add_argument("--past-actions", choices=("recorded", "zeros"), default=None,
                                  help="what a d2a policy's world model imagines from: the recorded past actions "
                                       "(default, as in training) or none (zeros, as after a reset)")
    bench_policy_fit.set_defaults(func=cmd_bench_policy_fit)

    bench_success = bench.add_parser("success", help="success rates of d2a / d2a-no-cfg / mp1 / dp3, both protocols")
    bench_success.add_argument("--preset", choices=("cpu", "paper"), default="cpu",
                               help="cpu: the cpu policy preset, 3 seeds, 5 evaluations + 100 final episodes; "
                                    "paper: the paper's networks and budget, 15 evaluations (GPU work)")
    bench_success.add_argument("--task", action="append", default=None,
                               help="default: hammer lever-pull assembly push stick-pull")
    bench_success.add_argument("--algo", action="append", default=None,
                               choices=ALGOS, help="default: d2a d2a-no-cfg mp1 dp3 mp1-state")
    bench_success.add_argument("--seed", type=NON_NEGATIVE, action="append", default=None, help="default: the preset's")
    bench_success.add_argument("--demos", type=POSITIVE, default=None,
                               help="demonstrations per cell (default 10): the first N of one collection per task, "
                                    "so cells of 1, 2, 5, ... in one workdir train on nested sets")
    bench_success.add_argument("--pool", type=POSITIVE, default=None,
                               help="demonstrations collected per task (default: --demos); a workdir with cells of "
                                    "several counts collects the largest, so world models validate on the rest")
    add_demo_seed_option(bench_success)
    bench_success.add_argument("--steps", type=POSITIVE, default=None, help="policy training steps (default: preset's)")
    add_policy_options(bench_success)
    bench_success.add_argument("--evaluations", type=POSITIVE, default=None,
                               help="periodic evaluations during training, the last at the final step; the paper "
                                    "protocol averages the best 5 (default: the preset's, cpu 5, paper 15)")
    add_eval_layouts_option(bench_success)
    bench_success.add_argument("--workers", type=POSITIVE, default=None, help="evaluation worker processes")
    bench_success.add_argument("--image-size", type=POSITIVE, default=None, help="depth image size of the data")
    bench_success.add_argument("--rgb-image-size", type=POSITIVE, default=None, metavar="PIXELS",
                               help="side of the colour images stored for an algo that reads them (dp; default 84)")
    bench_success.add_argument("--num-points", type=POSITIVE, default=None, help="points of the env's clouds")
    bench_success.add_argument("--backend", choices=("raycast", "render"), default=None)
    bench_success.add_argument("--world-model", choices=("demo", "cpu"), default=None,
                               help="demo: 32x32x8 Conv3d (the cpu preset's); cpu: d2a train-wm's 128x128x32 "
                                    "point-scatter (default: the preset's)")
    bench_success.add_argument("--wm-steps", type=POSITIVE, default=None, help="world-model training steps")
    add_world_model_data_options(bench_success)
    bench_success.add_argument("--dart-noise", type=NON_NEGATIVE_FLOAT, default=None, metavar="STD",
                               help="collect the demonstrations with DART noise (d2a collect --dart-noise); their "
                                    "data, world models and cells are named apart")
    bench_success.add_argument("--expert", choices=EXPERT_KINDS, default=None,
                               help="the Adroit tasks' expert (default: each task's own); its data, world models "
                                    "and cells are named apart")
    bench_success.add_argument("--action-draws", type=POSITIVE, default=None, metavar="K",
                               help="every evaluation acts on the mean of K chunks per plan (d2a eval "
                                    "--action-draws); cells named apart")
    bench_success.add_argument("--workdir", default=None,
                               help="data, models and finished cells; a rerun resumes")
    bench_success.add_argument("--cells", default=None,
                               help="where the finished cells' files go (default: WORKDIR/cells), e.g. a directory "
                                    "kept under version control; a rerun skips the cells found there")
    bench_success.add_argument("--threads", type=POSITIVE, default=None,
                               help="torch threads per cell; on Ray, the CPUs each cell asks for (default 1)")
    add_ray_option(bench_success)
    bench_success.set_defaults(func=cmd_bench_success)

    bench_table1 = bench.add_parser(
        "table1", help="the paper's Table I: Meta-World groups and Adroit x methods x seeds, resumable; "
                       "per-group table beside the paper's rows, CSV, plot")
    bench_table1.add_argument("--group", action="append", choices=("very_hard", "hard", "medium", "easy", "adroit"),
                              default=None, help="repeat for several (default: very_hard hard medium easy adroit, in "
                                                 "order; adroit: the three Adroit columns, at their own settings)")
    bench_table1.add_argument("--algo", action="append", choices=ALGOS, default=None, help="default: mp1 dp3")
    add_grid_options(bench_table1, "docs/table1", "outputs/table1")
    bench_table1.set_defaults(func=cmd_bench_table1)

    bench_table4 = bench.add_parser("table4", help="the paper's Table IV: success against 1-20 demonstrations on "
                                                   "its four tasks, resumable; the paper's layout, CSV, plot")
    bench_table4.add_argument("--task", action="append", default=None,
                              help="default: lever-pull assembly push stick-pull")
    bench_table4.add_argument("--demos", type=POSITIVE, action="append", default=None,
                              help="demonstration count; repeat (default 5 1 2 10 20, in order)")
    bench_table4.add_argument("--algo", action="append", choices=ALGOS, default=None,
                              help="default: mp1 d2a d2a-present")
    add_grid_options(bench_table4, "docs/table4", "outputs/table4")
    bench_table4.set_defaults(func=cmd_bench_table4)

    bench_paired = bench.add_parser("paired", help="one method against another on the cells they share (same task, "
                                                   "seed, settings, layouts): per pair and over pairs, intervals")
    add_cell_reading_options(bench_paired)
    bench_paired.add_argument("--algo", choices=ALGOS, default=None, help="default: d2a")
    bench_paired.add_argument("--control", choices=ALGOS, default=None, help="default: d2a-present")
    bench_paired.add_argument("--reference", choices=ALGOS, default=None,
                              help="a third method shown beside each pair and compared with --algo over the pairs "
                                   "that have its cell (default: mp1)")
    bench_paired.add_argument("--demos", type=POSITIVE, action="append", default=None,
                              help="only the cells trained on this many demonstrations (repeatable; default: all)")
    bench_paired.add_argument("--plot", default=None, help="a PNG of the per-pair differences (default: none)")
    bench_paired.add_argument("--runs", action="append", default=None, metavar="WORKDIR",
                              help="a grid's work directory (its runs/ hold the cells' checkpoints): each side's "
                                   "reliance on its second cloud for cells stored before they kept their own "
                                   "perception check (repeatable; default: none)")
    bench_paired.set_defaults(func=cmd_bench_paired)

    bench_order = bench.add_parser("order", help="does a claimed ranking of methods hold? each adjacent step "
                                                 "compared cell by cell, with intervals and a verdict")
    add_cell_reading_options(bench_order)
    bench_order.add_argument("--order", nargs="+", choices=ALGOS, required=True,
                             help="the claimed ranking, lowest first (e.g. dp cp dp3 flowpolicy mp1)")
    bench_order.add_argument("--plot", default=None,
                             help="a PNG of the methods on the cells all share and each step's verdict (default: none)")
    bench_order.set_defaults(func=cmd_bench_order)

    bench_ray = bench.add_parser("ray", help="the same small bench success grid on 1 and 2 Ray CPUs: wall time")
    bench_ray.add_argument("--task", default=None, help="default: reach")
    bench_ray.add_argument("--algo", choices=ALGOS, default=None, help="default: mp1")
    bench_ray.add_argument("--seed", type=NON_NEGATIVE, action="append", default=None, help="cells (default 0-3)")
    bench_ray.add_argument("--cpus", type=POSITIVE, action="append", default=None, help="Ray CPUs (default 1, 2)")
    bench_ray.add_argument("--steps", type=POSITIVE, default=None, help="policy training steps (default 300)")
    bench_ray.add_argument("--workdir", default=None)
    bench_ray.set_defaults(func=cmd_bench_ray)
