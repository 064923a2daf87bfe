"""The ``d2a`` command: one entry point, one subcommand per job."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from collectors.ray_jobs import JobsLost  # the standard library only: `d2a --help` stays fast

if TYPE_CHECKING:
    from d2a_agents.policy.checkpoints import Acting

# d2a_agents.policy.agent.ALGORITHMS, spelled out so that `d2a --help` does not import torch
ALGOS = ("d2a", "d2a-change", "d2a-change-top", "d2a-no-cfg", "d2a-no-imagination", "d2a-present", "d2a-oracle",
         "mp1", "dp3", "flowpolicy", "edm", "cp", "dp", "mp1-state", "dp3-state")
STATE_ALGOS = tuple(algo for algo in ALGOS if algo.endswith("-state"))  # the privileged-state references
EVAL_LAYOUTS = ("fixed", "fresh")  # d2a_agents.policy.train.EVAL_LAYOUTS, likewise
EXPERT_KINDS = ("controller", "planner")  # collectors.adroit_experts.EXPERT_KINDS, likewise


def _parse_box(text: str | None) -> tuple[tuple[float, ...], tuple[float, ...]] | None:
    if text is None:
        return None
    values = [float(v) for v in text.split(",")]
    if len(values) != 6:
        raise argparse.ArgumentTypeError("crop box must be six numbers: x0,y0,z0,x1,y1,z1")
    return tuple(values[:3]), tuple(values[3:])


def _int_at_least(minimum: int) -> Callable[[str], int]:
    """An argparse type: an integer >= ``minimum``, refused at the command line before any work."""

    def integer(text: str) -> int:
        value = int(text)  # a ValueError becomes argparse's "invalid integer value"
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be at least {minimum}, got {value}")
        return value

    return integer


def _finite_at_least(minimum: float) -> Callable[[str], float]:
    """An argparse type: a finite number >= ``minimum`` (nan and inf refused)."""

    def number(text: str) -> float:
        value = float(text)
        if not minimum <= value < float("inf"):
            raise argparse.ArgumentTypeError(f"must be a finite number >= {minimum:g}, got {text}")
        return value

    return number


POSITIVE, NON_NEGATIVE = _int_at_least(1), _int_at_least(0)
NON_NEGATIVE_FLOAT = _finite_at_least(0.0)


DEMOS_HELP = "train on the first N episodes of each task (default: all); runs on 1, 2, 5 ... of one data set nest"


def _add_env_options(parser: argparse.ArgumentParser, several_tasks: bool = False) -> None:
    if several_tasks:
        parser.add_argument("--task", action="append", required=True, help="task name or env id; repeat for several")
    else:
        parser.add_argument("--task", default="hammer", help="task name or env id (see `d2a tasks`)")
    parser.add_argument("--seed", type=NON_NEGATIVE, default=0)
    parser.add_argument("--action-repeat", type=POSITIVE, default=None,
                        help="hold each action for this many simulator steps (DP3's Adroit envs: 2; default 1)")
    _add_cloud_options(parser)


def _add_cloud_options(parser: argparse.ArgumentParser) -> None:
    """The env options that shape its clouds (read back by ``_env_kwargs``)."""
    parser.add_argument("--backend", choices=("raycast", "render"), default=None)
    parser.add_argument("--cameras", default=None, help="comma-separated camera names, fused in the world frame")
    parser.add_argument("--image-size", type=POSITIVE, default=None)
    parser.add_argument("--num-points", type=POSITIVE, default=None)
    parser.add_argument("--crop-box", type=_parse_box, default=None, help="x0,y0,z0,x1,y1,z1 in metres")
    parser.add_argument("--hide-sites", action="store_true", help="leave MuJoCo sites (goal markers) out")
    parser.add_argument("--rgb-image-size", type=POSITIVE, default=None, metavar="PIXELS",
                        help="add the first camera's colour image (PIXELS a side) to the observations: what "
                             "--algo dp reads (stored per step by d2a collect; lit with --backend render)")


def _add_ray_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--ray", nargs="?", const="local", default=None, metavar="ADDRESS",
                        help="run the episodes (or cells) as Ray jobs: alone, on a Ray instance started on this "
                             "machine; 'auto': the running cluster; or a cluster address (needs the ray extra)")


def _add_acting_options(parser: argparse.ArgumentParser) -> None:
    """How a checkpoint acts (``Acting``): actions per planned chunk, draws per chunk."""
    parser.add_argument("--n-action-steps", type=POSITIVE, default=None,
                        help="actions executed per planned chunk before planning again (default: the "
                             "checkpoint's; 1 plans after every action)")
    parser.add_argument("--action-draws", type=POSITIVE, default=1, metavar="K",
                        help="chunks drawn from independent noise per plan, acted on as their mean (default 1)")
    parser.add_argument("--sample-steps", type=POSITIVE, default=None, metavar="K",
                        help="network evaluations per drawn chunk (default: the expert's own; one for mp1, "
                             "d2a, flowpolicy, cp)")


def _acting(args: argparse.Namespace) -> Acting:
    """The ``Acting`` that :func:`_add_acting_options` read."""
    from d2a_agents.policy.checkpoints import Acting

    return Acting(args.n_action_steps, args.action_draws, args.sample_steps)


def _add_eval_layouts_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--eval-layouts", choices=EVAL_LAYOUTS, default=None,
                        help="fixed: every periodic evaluation on the same layouts (default); fresh: new layouts "
                             "at each, as DP3's and MP1's runners (the paper protocol's best 5 then also "
                             "select over layout draws)")


def _add_grid_options(parser: argparse.ArgumentParser, results: str, workdir: str) -> None:
    """The options every grid bench (table1, table4) shares."""
    parser.add_argument("--seed", type=NON_NEGATIVE, action="append", default=None, help="default: 0 1 2")
    parser.add_argument("--steps", type=POSITIVE, default=None, help="policy training steps (default: preset's)")
    _add_policy_options(parser)
    parser.add_argument("--evaluations", type=POSITIVE, default=None, help="periodic evaluations (default 5)")
    _add_eval_layouts_option(parser)
    parser.add_argument("--workers", type=POSITIVE, default=None, help="evaluation worker processes")
    parser.add_argument("--workdir", default=None, help=f"data, world models, checkpoints (default {workdir})")
    parser.add_argument("--results", default=None,
                        help=f"finished cells and the report (default {results}); a rerun skips its cells")
    parser.add_argument("--threads", type=POSITIVE, default=None, help="torch threads per cell (default 1)")
    parser.add_argument("--report", action="store_true", help="only write the report of the finished cells")
    _add_ray_option(parser)


def _add_policy_options(parser: argparse.ArgumentParser) -> None:
    """The policy's point budget, the oracle's horizons and the MeanFlow network's output (in a
    success bench, cells of a changed preset are named by what differs from the ``cpu`` preset,
    e.g. ``..._num_points128``)."""
    parser.add_argument("--policy-points", type=POSITIVE, default=None,
                        help="points per cloud the encoders read, farthest-point sampled from the data's clouds "
                             "(default: the preset's, cpu 64; the env's cloud size is the data's)")
    parser.add_argument("--imagined-points", type=POSITIVE, default=None,
                        help="points of the second cloud (the imagined one, or d2a-present's copy of the present; "
                             "default: --policy-points)")
    parser.add_argument("--oracle-horizon", type=POSITIVE, default=None,
                        help="steps ahead of d2a-oracle's true future cloud (default 4, the world models' horizon)")
    parser.add_argument("--stacked-horizon", type=POSITIVE, action="append", default=None, dest="stacked_horizons",
                        help="a further horizon whose true future cloud d2a-oracle reads beside --oracle-horizon's "
                             "(repeatable: --stacked-horizon 1 --stacked-horizon 2 stacks H = 1, 2, 4)")
    parser.add_argument("--meanflow-output", choices=("velocity", "action"), default=None,
                        help="what a MeanFlow network outputs: the average velocity (default, as MP1) or the clean "
                             "action chunk, read as the velocity it implies")


def _with_policy_options(bench: Any, args: argparse.Namespace) -> Any:
    """A success bench's per-cell settings with the policy options given (steps, point budget,
    oracle horizons, MeanFlow output)."""
    policy = _replace_given(bench.policy.policy, num_points=args.policy_points, imagined_points=args.imagined_points,
                            oracle_horizon=args.oracle_horizon, stacked_horizons=_stacked(args),
                            meanflow_output=args.meanflow_output)
    return dataclasses.replace(bench, policy=_replace_given(bench.policy, steps=args.steps, policy=policy))


def _stacked(args: argparse.Namespace) -> tuple[int, ...] | None:
    """The ``--stacked-horizon`` values as the policy setting (``None``: not given)."""
    return tuple(args.stacked_horizons) if args.stacked_horizons else None


def _replace_given(instance: Any, **changes: object) -> Any:
    """``dataclasses.replace`` with the options the user gave (``None``: keep the default)."""
    return dataclasses.replace(instance, **{k: v for k, v in changes.items() if v is not None})


def _env_kwargs(args: argparse.Namespace) -> dict[str, object]:
    kwargs = dict(backend=args.backend, image_size=args.image_size, num_points=args.num_points, crop_box=args.crop_box,
                  rgb_image_size=args.rgb_image_size,
                  action_repeat=getattr(args, "action_repeat", None))  # an env option; data import has none
    if args.cameras:
        kwargs["cameras"] = tuple(args.cameras.split(","))
    if args.hide_sites:
        kwargs["show_sites"] = False
    return {k: v for k, v in kwargs.items() if v is not None}


def cmd_tasks(args: argparse.Namespace) -> None:
    import d2a_envs

    specs = d2a_envs.list_tasks(suite=args.suite, difficulty=args.difficulty, table1=True if args.table1 else None)
    print(f"{'env id':<42} {'name':<28} {'suite':<10} {'difficulty':<11} table I")
    for spec in specs:
        print(f"{spec.env_id:<42} {spec.name:<28} {spec.suite:<10} {spec.difficulty or '-':<11} "
              f"{'yes' if spec.table1 else '-'}")
    print(f"{len(specs)} tasks")


def cmd_viz_pointcloud(args: argparse.Namespace) -> None:
    import d2a_envs  # noqa: F401  (registers the ids)
    from d2a_envs.viz import plot_task_point_cloud

    path = plot_task_point_cloud(args.task, args.out, seed=args.seed, steps=args.steps, **_env_kwargs(args))
    print(f"wrote {path}")


def cmd_bench_envs(args: argparse.Namespace) -> None:
    from benchmarks.envs import EnvBenchConfig, run

    run(_replace_given(EnvBenchConfig(), task=args.task, steps=args.steps, seed=args.seed))


def cmd_collect(args: argparse.Namespace) -> None:
    from collectors.collect import CollectConfig, collect

    config = _replace_given(
        CollectConfig(tasks=tuple(args.task), out=args.out, env_kwargs=_env_kwargs(args), append=args.append,
                      overwrite=args.overwrite, ray_address=args.ray),
        episodes=args.episodes, seed=args.seed, max_attempts_factor=args.max_attempts_factor,
        max_episode_steps=args.max_episode_steps, action_noise=args.action_noise,
        keep_failures=True if args.keep_failures else None, expert=args.expert, dart_noise=args.dart_noise,
    )
    dataset = collect(config)
    print(f"wrote {dataset.num_frames} steps in {len(dataset.metadata.episodes)} episodes to {dataset.directory}")


def cmd_data_info(args: argparse.Namespace) -> None:
    from collectors.storage import DemoDataset, describe

    print(describe(DemoDataset.open(args.dir)))


def cmd_data_import(args: argparse.Namespace) -> None:
    from collectors.storage import describe

    if args.dp3:
        from collectors.dp3_format import import_dp3

        if args.task is None:
            raise ValueError("--dp3 needs --task: the task its episodes show")
        dataset = import_dp3(args.dp3, args.out, args.task, _env_kwargs(args) or None, overwrite=args.overwrite)
    elif args.lerobot:
        import d2a_envs
        from collectors.lerobot_format import import_lerobot

        if args.task is None:
            raise ValueError("--lerobot needs --task: the task its episodes show")
        suite = d2a_envs.SUITE_DEFAULTS[d2a_envs.get_task(args.task).suite]
        dataset = import_lerobot(
            args.lerobot, args.out, args.task, cloud_key=args.cloud_key, depth_key=args.depth_key, camera=args.camera,
            depth_scale=args.depth_scale, crop_box=args.crop_box or suite.crop_box,
            num_points=args.num_points or suite.num_points, state_key=args.state_key,
            full_state_key=args.full_state_key, env_kwargs=_env_kwargs(args) or None, overwrite=args.overwrite)
    else:
        import json

        import d2a_envs
        from collectors.recording import import_recording

        task = json.loads((Path(args.recording) / "recording.json").read_text())["task"]
        suite = d2a_envs.SUITE_DEFAULTS[d2a_envs.get_task(task).suite]
        dataset = import_recording(args.recording, args.out, crop_box=args.crop_box or suite.crop_box,
                                   num_points=args.num_points or suite.num_points, overwrite=args.overwrite)
    print(describe(dataset))


def cmd_data_export(args: argparse.Namespace) -> None:
    from collectors.dp3_format import export_dp3

    print(f"wrote {export_dp3(args.dir, args.dp3, overwrite=args.overwrite)}")


def cmd_act(args: argparse.Namespace) -> None:
    import gymnasium as gym

    import d2a_envs
    from d2a_agents.deploy import DeploymentLoop, SimCameras, SimRobot
    from d2a_agents.policy.checkpoints import load_checkpoint, policy_file

    payload = load_checkpoint(policy_file(args.policy), "policy")
    task = args.task or payload["tasks"][0]
    env_kwargs = {k: v for k, v in payload["env_kwargs"][task].items() if k != "max_episode_steps"}
    env = gym.make(d2a_envs.get_task(task).env_id, **env_kwargs)
    cameras = SimCameras(env)
    robot = SimRobot(env.unwrapped, seed=args.seed)  # the bare simulator: the cameras above draw the clouds
    try:
        rate = {} if args.hz is None else {"hz": args.hz}
        log = DeploymentLoop(args.policy, cameras, robot, seed=args.seed, pixel_stride=args.pixel_stride,
                             acting=_acting(args), **rate).run(args.steps)
    finally:
        cameras.close()
        env.close()
    print(log.summary())
    print(f"the simulated {task} reported success on {robot.successes} of {len(log.steps)} steps")


def cmd_report(args: argparse.Namespace) -> None:
    from d2a_agents.checkpoint import CheckpointError
    from d2a_agents.policy.report import format_report, plot_report, read_run, report_rows

    outcomes = []
    for run in args.runs:  # a shell glob may bring in world models and empty folders: say so, go on
        try:
            found = read_run(run)
        except CheckpointError as error:
            print(f"skipped {run}: {error}", file=sys.stderr)
            continue
        if not found:
            print(f"skipped {run}: still training, or not evaluated at its last step", file=sys.stderr)
        outcomes += found
    if not outcomes:
        raise SystemExit("no evaluated run among the given ones")
    rows = report_rows(outcomes)
    print(format_report(rows))
    if args.plot:
        print(f"wrote {plot_report(rows, args.plot)}")


def cmd_train_wm(args: argparse.Namespace) -> None:
    from d2a_agents.world_model.train import TrainWorldModelConfig, train_world_model
    from d2a_agents.world_model.triplane import CPU_PRESET, WorldModelConfig

    base = CPU_PRESET if args.preset == "cpu" else WorldModelConfig()
    model = _replace_given(base, horizon=args.horizon, action_history=args.history, channels=args.channels,
                           feature_mode=args.feature_mode, plane_pooling=args.plane_pooling, encoder=args.encoder,
                           resolution=tuple(args.resolution) if args.resolution else None)
    config = _replace_given(
        TrainWorldModelConfig(data=args.data, out=args.out, model=model), steps=args.steps,
        batch_size=args.batch_size, learning_rate=args.lr, queries=args.queries, validate_every=args.validate_every,
        seed=args.seed, device=args.device, threads=args.threads, demos=args.demos,
        with_rollouts=True if args.with_rollouts else None,
    )
    _, history = train_world_model(config)
    if history:
        last = history[-1]
        print(f"held-out full-grid IoU {last.full_iou:.3f} (persistence {last.persistence_full_iou:.3f}), "
              f"dynamic IoU {last.dynamic_iou:.3f}, over {last.transitions} transitions, threshold {last.threshold}")


def cmd_viz_imagine(args: argparse.Namespace) -> None:
    import d2a_envs  # noqa: F401  (registers the ids)
    from d2a_agents.world_model.viz import plot_task_imagination

    steps = tuple(int(step) for step in args.steps.split(","))
    path = plot_task_imagination(args.world_model, args.task, args.out, args.seed, steps, **_env_kwargs(args))
    print(f"wrote {path}")


def cmd_train_policy(args: argparse.Namespace) -> None:
    from d2a_agents.policy.train import POLICY_PRESETS, TrainPolicyConfig, train_policy

    preset = _replace_given(POLICY_PRESETS[args.preset], steps=args.steps, batch_size=args.batch_size,
                            image_batch_size=args.batch_size, learning_rate=args.lr, image_learning_rate=args.lr,
                            trim_after_success=args.trim_after_success)
    policy = _replace_given(preset.policy, algo=args.algo, horizon=args.horizon, n_obs_steps=args.n_obs_steps,
                            n_action_steps=args.n_action_steps, num_points=args.policy_points,
                            imagined_points=args.imagined_points, oracle_horizon=args.oracle_horizon,
                            stacked_horizons=_stacked(args), cfg_similarity=args.cfg_similarity,
                            adaptive_power=args.adaptive_power, cfg_guidance=args.cfg_guidance,
                            cfg_scale=args.cfg_scale, meanflow_output=args.meanflow_output,
                            cfg_thresholds=tuple(args.cfg_thresholds) if args.cfg_thresholds else None)
    config = _replace_given(
        TrainPolicyConfig.from_preset(preset, data=args.data, out=args.out, policy=policy,
                                      world_model=args.world_model, teacher=args.teacher),
        eval_every=args.eval_every, eval_episodes=args.eval_episodes, eval_layouts=args.eval_layouts,
        eval_workers=args.workers, seed=args.seed, holdout_episodes=args.holdout_episodes, device=args.device,
        threads=args.threads, logger=args.logger, augment_shift=args.augment_shift, demos=args.demos,
    )
    _, history = train_policy(config)
    for point in history:
        print(f"step {point.step}: success {point.success_rate:.0%} over {point.episodes} episodes")


def cmd_eval(args: argparse.Namespace) -> None:
    env_kwargs = _env_kwargs(args)
    if args.policy == "expert":
        import functools

        from collectors.evaluation import evaluate
        from collectors.experts import ExpertSettings, expert_env_kwargs, make_expert

        if args.n_action_steps is not None or args.action_draws != 1 or args.sample_steps is not None:
            raise ValueError("--n-action-steps, --action-draws and --sample-steps apply to a policy checkpoint; "
                             "the expert acts step by step")
        make = functools.partial(make_expert, args.task, ExpertSettings(kind=args.expert))
        make()  # a task without that expert fails here, before any worker starts
        result = evaluate(make, args.task, args.episodes, args.seed,
                          env_kwargs={**env_kwargs, **expert_env_kwargs(args.task)}, workers=args.workers,
                          end_on_success=args.end_on_success, ray_address=args.ray)
    else:
        from d2a_agents.policy.checkpoints import evaluate_checkpoint

        if args.expert is not None:
            raise ValueError("--expert applies to --policy expert")
        if env_kwargs:
            raise ValueError(f"{args.policy} is evaluated in the env it was trained with; "
                             f"the env options ({', '.join(env_kwargs)}) apply to --policy expert only")
        result = evaluate_checkpoint(args.policy, args.task, args.episodes, args.seed, workers=args.workers,
                                     end_on_success=args.end_on_success, ray_address=args.ray,
                                     acting=_acting(args))
    print(result.summary())


def cmd_bench_experts(args: argparse.Namespace) -> None:
    from benchmarks.experts import ExpertBenchConfig, run

    base = ExpertBenchConfig()
    run(_replace_given(base, tasks=tuple(args.task) if args.task else None, episodes=args.episodes,
                       workers=args.workers, ray_address=args.ray, imitation_demos=args.imitation_demos,
                       imitation_episodes=args.imitation_episodes, workdir=args.workdir,
                       imitation_dart_noise=args.imitation_dart_noise,
                       imitation_action_draws=args.imitation_action_draws, imitation_algo=args.imitation_algo))


def cmd_bench_tune_expert(args: argparse.Namespace) -> None:
    from benchmarks.tune_expert import TuneConfig, run

    run(_replace_given(TuneConfig(), task=args.task, iterations=args.iterations, episodes=args.episodes,
                       first_seed=args.first_seed, seed=args.seed, noise=args.noise, out=args.out))


def cmd_bench_latency(args: argparse.Namespace) -> None:
    from benchmarks.latency import LatencyBenchConfig, run

    run(_replace_given(LatencyBenchConfig(), task=args.task, num_points=args.num_points, repeats=args.repeats,
                       world_model=args.world_model, data=args.data))


def cmd_bench_train(args: argparse.Namespace) -> None:
    from benchmarks.train import TrainBenchConfig, run

    run(_replace_given(TrainBenchConfig(), steps=args.steps, threads=args.threads, device=args.device))


def cmd_bench_ablate(args: argparse.Namespace) -> None:
    from benchmarks.ablation import AblationConfig, run, table

    if args.table:
        print(table(args.workdir or AblationConfig.workdir))
        return
    if not (args.data and args.task):
        raise ValueError("bench ablate needs --data and --task (or --table)")
    run(_replace_given(AblationConfig(data=args.data, task=args.task), change=args.change, algo=args.algo,
                       seed=args.seed, world_model=args.world_model, episodes=args.episodes, workdir=args.workdir))


def cmd_bench_wm(args: argparse.Namespace) -> None:
    from benchmarks.world_model import BENCH_MODELS, BenchModel, WorldModelBenchConfig, run

    main, baseline = BENCH_MODELS
    model = _replace_given(main.model, plane_pooling=args.plane_pooling, encoder=args.encoder,
                           feature_mode=args.mode, resolution=tuple(args.resolution) if args.resolution else None)
    label = f"{'x'.join(map(str, model.resolution))} {model.encoder}" + (
        "" if model.feature_mode == "triplane" else f" {model.feature_mode}")
    models = (BenchModel(label, model, args.steps or main.steps),)
    if args.baseline_steps != 0:
        models += (dataclasses.replace(baseline, steps=args.baseline_steps or baseline.steps),)
    base = WorldModelBenchConfig()
    env_kwargs = {**base.env_kwargs, **{key: value for key, value in (
        ("num_points", args.num_points), ("image_size", args.image_size), ("backend", args.backend)) if value}}
    run(_replace_given(base, tasks=tuple(args.task) if args.task else None, models=models, env_kwargs=env_kwargs,
                       horizons=tuple(args.horizon) if args.horizon else None, workdir=args.workdir))


def cmd_bench_fusion(args: argparse.Namespace) -> None:
    from benchmarks.fusion import FusionBenchConfig, run

    run(_replace_given(FusionBenchConfig(), repeats=args.repeats))


def cmd_bench_change(args: argparse.Namespace) -> None:
    from benchmarks.change import ChangeBenchConfig, run

    run(_replace_given(ChangeBenchConfig(world_model=args.world_model, data=args.data), demos=args.demos,
                       stride=args.stride, num_points=args.points))


def cmd_bench_wm_fit(args: argparse.Namespace) -> None:
    from benchmarks.world_model_fit import WorldModelFitConfig, run

    run(_replace_given(WorldModelFitConfig(world_model=args.world_model, data=args.data, demos=args.demos),
                       stride=args.stride))


def cmd_bench_success(args: argparse.Namespace) -> None:
    from benchmarks.success import PRESETS, run

    base = _with_policy_options(PRESETS[args.preset], args)
    env_kwargs = {k: v for k, v in dict(image_size=args.image_size, num_points=args.num_points,
                                        backend=args.backend).items() if v is not None}
    world_model = None
    if args.world_model is not None:
        from d2a_agents.world_model.triplane import CPU_PRESET, WorldModelConfig

        # cpu: d2a train-wm's cpu preset (128x128x32, point-scatter); demo: the demo's 32x32x8 Conv3d
        world_model = CPU_PRESET if args.world_model == "cpu" else WorldModelConfig(resolution=(32, 32, 8))
    run(_replace_given(
        base, tasks=tuple(args.task) if args.task else None,
        algos=tuple(args.algo) if args.algo else None, seeds=tuple(args.seed) if args.seed else None,
        workdir=args.workdir, workers=args.workers, env_kwargs=env_kwargs or None, world_model=world_model,
        world_model_steps=args.wm_steps, threads=args.threads, ray_address=args.ray, evaluations=args.evaluations,
        eval_layouts=args.eval_layouts, demos=args.demos, pool=args.pool, cells=args.cells,
        wm_rollouts=args.wm_rollouts, rollout_noise=args.rollout_noise, dart_noise=args.dart_noise,
        action_draws=args.action_draws, rgb_image_size=args.rgb_image_size,
    ))


def _grid_cells(base: Any, args: argparse.Namespace) -> Any:
    """A grid bench's per-cell settings (``SuccessBenchConfig``) with the options given."""
    return _replace_given(_with_policy_options(base, args), workdir=args.workdir, threads=args.threads,
                          ray_address=args.ray, evaluations=args.evaluations, eval_layouts=args.eval_layouts,
                          workers=args.workers)


def cmd_bench_table1(args: argparse.Namespace) -> None:
    from benchmarks.table1 import Table1Config, run

    base = Table1Config()
    run(_replace_given(base, groups=tuple(args.group) if args.group else None,
                       algos=tuple(args.algo) if args.algo else None, seeds=tuple(args.seed) if args.seed else None,
                       results=args.results, bench=_grid_cells(base.bench, args)), report_only=args.report)


def cmd_bench_table4(args: argparse.Namespace) -> None:
    from benchmarks.table4 import Table4Config, run

    base = Table4Config()
    run(_replace_given(base, tasks=tuple(args.task) if args.task else None,
                       demos=tuple(args.demos) if args.demos else None,
                       algos=tuple(args.algo) if args.algo else None, seeds=tuple(args.seed) if args.seed else None,
                       results=args.results, bench=_grid_cells(base.bench, args)), report_only=args.report)


def cmd_bench_paired(args: argparse.Namespace) -> None:
    from benchmarks.paired import PairedConfig, run

    run(_replace_given(PairedConfig(results=tuple(args.results)), algo=args.algo, control=args.control,
                       plot=args.plot))


def cmd_bench_ray(args: argparse.Namespace) -> None:
    from benchmarks.ray_scaling import RayScalingConfig, run

    base = RayScalingConfig()
    run(_replace_given(base, task=args.task, algo=args.algo, seeds=tuple(args.seed) if args.seed else None,
                       cpus=tuple(args.cpus) if args.cpus else None, workdir=args.workdir,
                       policy=_replace_given(base.policy, steps=args.steps)))


def cmd_demo(args: argparse.Namespace) -> None:
    from d2a.demo import DemoConfig, run_demo

    base = DemoConfig()
    run_demo(_replace_given(
        base, task=args.task, out=args.out, episodes=args.episodes, world_model_steps=args.wm_steps,
        policy=_replace_given(base.policy, steps=args.policy_steps), eval_episodes=args.eval_episodes,
        seed=args.seed, threads=args.threads,
    ))


class _Parser(argparse.ArgumentParser):
    """Refuses abbreviated options (``--out`` must not silently stand for another ``--out...``);
    sub-commands inherit the class."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **{**kwargs, "allow_abbrev": False})


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="d2a", description="D2A: imagine the 3D future, then act.")
    commands = parser.add_subparsers(dest="command", required=True)

    tasks = commands.add_parser("tasks", help="list the registered tasks")
    tasks.add_argument("--suite", choices=("metaworld", "adroit"), default=None)
    tasks.add_argument("--difficulty", choices=("easy", "medium", "hard", "very_hard"), default=None)
    tasks.add_argument("--table1", action="store_true", help="only the 37 tasks of the paper's Table I")
    tasks.set_defaults(func=cmd_tasks)

    viz = commands.add_parser("viz", help="pictures").add_subparsers(dest="what", required=True)
    pointcloud = viz.add_parser("pointcloud", help="point cloud and crop box, several views")
    _add_env_options(pointcloud)
    pointcloud.add_argument("--steps", type=NON_NEGATIVE, default=0, help="random steps before the picture")
    pointcloud.add_argument("--out", required=True)
    pointcloud.set_defaults(func=cmd_viz_pointcloud)

    imagine = viz.add_parser("imagine", help="current, imagined and true future clouds over an episode")
    _add_env_options(imagine)
    imagine.add_argument("--world-model", required=True, help="checkpoint of d2a train-wm")
    imagine.add_argument("--steps", default="10,40,70,100,130", help="comma-separated control steps to draw")
    imagine.add_argument("--out", required=True)
    imagine.set_defaults(func=cmd_viz_imagine)

    bench = commands.add_parser("bench", help="benchmarks (print figures)").add_subparsers(dest="what", required=True)
    bench_envs = bench.add_parser("envs", help="env steps/s per depth backend")
    bench_envs.add_argument("--task", default=None)
    bench_envs.add_argument("--steps", type=POSITIVE, default=None)
    bench_envs.add_argument("--seed", type=NON_NEGATIVE, default=None)
    bench_envs.set_defaults(func=cmd_bench_envs)

    collect = commands.add_parser("collect", help="expert demonstrations (scripted, controller or planner) into a "
                                                  "data set")
    _add_env_options(collect, several_tasks=True)
    collect.add_argument("--episodes", type=POSITIVE, default=None, help="successful episodes to keep per task")
    collect.add_argument("--out", required=True, help="data set directory")
    collect.add_argument("--max-attempts-factor", type=POSITIVE, default=None, help="give up after episodes x this "
                         "(default 3; 10 with --dart-noise, whose perturbed expert fails more often)")
    collect.add_argument("--max-episode-steps", type=POSITIVE, default=None)
    collect.add_argument("--action-noise", type=NON_NEGATIVE_FLOAT, default=None, metavar="STD",
                         help="Gaussian noise added to the expert's actions: rollouts for a world model, never "
                              "trained on by policies (with --keep-failures)")
    collect.add_argument("--keep-failures", action="store_true", help="store every attempt, not only successes")
    collect.add_argument("--dart-noise", type=NON_NEGATIVE_FLOAT, default=None, metavar="STD",
                         help="Gaussian noise on the executed actions while the stored labels stay the expert's "
                              "(DART): demonstrations that also show how the expert recovers")
    collect.add_argument("--expert", choices=EXPERT_KINDS, default=None,
                         help="Adroit: the state-feedback controller (default where the task has one) or the "
                              "predictive-sampling planner")
    mode = collect.add_mutually_exclusive_group()
    mode.add_argument("--append", action="store_true", help="add to (or resume) an existing data set")
    mode.add_argument("--overwrite", action="store_true", help="replace an existing data set")
    _add_ray_option(collect)
    collect.set_defaults(func=cmd_collect)

    train_wm = commands.add_parser("train-wm", help="train the triplane world model on a data set")
    train_wm.add_argument("--data", required=True, help="data set directory (d2a collect)")
    train_wm.add_argument("--out", required=True, help="checkpoint file; an existing one is resumed")
    train_wm.add_argument("--preset", choices=("cpu", "paper"), default="cpu",
                          help="cpu: 128x128x32, point-scatter encoder; paper: 128x128x32, Conv3d encoder (GPU work)")
    train_wm.add_argument("--resolution", type=POSITIVE, nargs=3, default=None, metavar=("X", "Y", "Z"))
    train_wm.add_argument("--horizon", type=POSITIVE, default=None, help="H, steps imagined ahead")
    train_wm.add_argument("--history", type=POSITIVE, default=None, help="past actions conditioning the model")
    train_wm.add_argument("--channels", type=POSITIVE, default=None, help="feature dimension C")
    train_wm.add_argument("--feature-mode", choices=("triplane", "xy", "volume"), default=None)
    train_wm.add_argument("--plane-pooling", choices=("mean", "max"), default=None,
                          help="how the feature volume collapses onto each plane (default: the preset's)")
    train_wm.add_argument("--encoder", choices=("volume-conv", "point-scatter"), default=None,
                          help="volume-conv: Conv3d over the grid (the paper); point-scatter: per-voxel MLP "
                               "scattered onto the planes, cost follows the occupied voxels")
    train_wm.add_argument("--demos", type=POSITIVE, default=None, help=DEMOS_HELP)
    train_wm.add_argument("--with-rollouts", action="store_true",
                          help="also train on the data set's rollouts (d2a collect --action-noise --keep-failures)")
    train_wm.add_argument("--steps", type=POSITIVE, default=None)
    train_wm.add_argument("--batch-size", type=POSITIVE, default=None)
    train_wm.add_argument("--lr", type=float, default=None)
    train_wm.add_argument("--queries", type=POSITIVE, default=None)
    train_wm.add_argument("--validate-every", type=POSITIVE, default=None)
    train_wm.add_argument("--seed", type=NON_NEGATIVE, default=None)
    train_wm.add_argument("--device", default=None, help="cpu or cuda")
    train_wm.add_argument("--threads", type=NON_NEGATIVE, default=None, help="torch threads (0: torch's own)")
    train_wm.set_defaults(func=cmd_train_wm)

    train_policy = commands.add_parser("train-policy", help="train a policy (d2a, mp1, dp3, ablations)")
    train_policy.add_argument("--data", required=True)
    train_policy.add_argument("--out", required=True, help="run directory; an existing run is resumed")
    train_policy.add_argument("--algo", choices=ALGOS, default="d2a",
                              help="mp1-state, dp3-state: the privileged-state references (no cloud; the perception "
                                   "upper bound); dp: the 2D Diffusion Policy (data collected with --rgb-image-size)")
    train_policy.add_argument("--world-model", default=None, help="checkpoint of d2a train-wm (d2a variants)")
    train_policy.add_argument("--teacher", default=None,
                              help="--algo cp: the EDM teacher it distils (policy.pt of --algo edm, same data)")
    train_policy.add_argument("--preset", choices=("cpu", "paper"), default="cpu",
                              help="networks and budget: cpu (64 points, narrow, 4000 steps of 256, lr 1e-3) or "
                                   "paper (1024 points, 47k steps of 128, lr 1e-4; GPU work)")
    train_policy.add_argument("--demos", type=POSITIVE, default=None, help=DEMOS_HELP)
    train_policy.add_argument("--steps", type=POSITIVE, default=None, help="default: the preset's")
    train_policy.add_argument("--batch-size", type=POSITIVE, default=None, help="default: the preset's")
    train_policy.add_argument("--lr", type=float, default=None, help="default: the preset's")
    train_policy.add_argument("--horizon", type=POSITIVE, default=None, help="action chunk length (default 4)")
    train_policy.add_argument("--n-obs-steps", type=POSITIVE, default=None, help="default 2")
    train_policy.add_argument("--n-action-steps", type=POSITIVE, default=None, help="default 4")
    _add_policy_options(train_policy)
    train_policy.add_argument("--cfg-similarity", choices=("velocity", "prediction"), default=None,
                              help="rho of the adaptive CFG gate: cos(u_cond, u_null) (default) or cos(v, u_null) "
                                   "with v the sampled velocity (MeanFlow's CFG reading)")
    train_policy.add_argument("--cfg-thresholds", type=float, nargs=2, default=None, metavar=("TAU_L", "TAU_H"),
                              help="eq. 7 thresholds (default -1 0)")
    train_policy.add_argument("--cfg-guidance", choices=("interpolate", "amplify"), default=None,
                              help="interpolate: eq. 6 as written (towards the unconditional field, default); "
                                   "amplify: mixing weight 1 + cfg_scale * w (away from it, as MeanFlow guides)")
    train_policy.add_argument("--cfg-scale", type=float, default=None, help="k of --cfg-guidance amplify (default 1)")
    train_policy.add_argument("--adaptive-power", type=float, default=None,
                              help="MeanFlow's adaptive loss power p (0: plain squared error; default: the preset's)")
    train_policy.add_argument("--trim-after-success", type=int, default=None, metavar="K",
                              help="keep K frames after each demonstration's first success (-1: all; "
                                   "default: the preset's)")
    train_policy.add_argument("--augment-shift", type=NON_NEGATIVE_FLOAT, default=None, metavar="METRES",
                              help="move each training window's clouds and end effector by a random translation "
                                   "in the table plane of up to this along x and y (Meta-World only; default: the "
                                   "preset's, cpu 0.02 on Meta-World and off elsewhere, paper off; 0: off)")
    train_policy.add_argument("--logger", default=None, choices=["csv", "tensorboard", "wandb", "mlflow", ""],
                              help="TorchRL logger of the scalars under OUT/logs ('': none; default csv)")
    train_policy.add_argument("--holdout-episodes", type=NON_NEGATIVE, default=None,
                              help="hold out the last K episodes of each task for the perception check")
    train_policy.add_argument("--device", default=None, help="cpu or cuda (evaluation runs on the CPU)")
    train_policy.add_argument("--threads", type=NON_NEGATIVE, default=None, help="torch threads (0: torch's own)")
    train_policy.add_argument("--eval-every", type=NON_NEGATIVE, default=None, help="0: evaluate at the end only")
    train_policy.add_argument("--eval-episodes", type=NON_NEGATIVE, default=None)
    _add_eval_layouts_option(train_policy)
    train_policy.add_argument("--workers", type=POSITIVE, default=None)
    train_policy.add_argument("--seed", type=NON_NEGATIVE, default=None)
    train_policy.set_defaults(func=cmd_train_policy)

    evaluation = commands.add_parser("eval", help="evaluate a policy checkpoint (or the task's expert)")
    _add_env_options(evaluation)
    evaluation.add_argument("--policy", required=True, help="policy.pt of d2a train-policy, or 'expert'")
    evaluation.add_argument("--expert", choices=EXPERT_KINDS, default=None,
                            help="with --policy expert on Adroit: the controller (default where the task has one) "
                                 "or the planner")
    evaluation.add_argument("--episodes", type=POSITIVE, default=100)
    evaluation.add_argument("--workers", type=POSITIVE, default=2)
    evaluation.add_argument("--end-on-success", action="store_true",
                            help="end episodes at their first success (same success rate, faster; returns stop there)")
    _add_acting_options(evaluation)
    _add_ray_option(evaluation)
    evaluation.set_defaults(func=cmd_eval)

    act = commands.add_parser("act", help="run a checkpoint at a fixed control rate on a robot (here the simulated "
                                          "one; your own through d2a_agents.deploy's interfaces); Ctrl-C stops")
    act.add_argument("--policy", required=True, help="policy.pt of d2a train-policy (or its run directory)")
    act.add_argument("--task", default=None, help="default: the policy's first task")
    act.add_argument("--steps", type=POSITIVE, default=None, help="control steps (default: until Ctrl-C)")
    act.add_argument("--hz", type=_finite_at_least(0.001), default=None, help="control rate (default 10)")
    act.add_argument("--seed", type=NON_NEGATIVE, default=0, help="the simulated scene's layout")
    act.add_argument("--pixel-stride", type=POSITIVE, default=1, metavar="K",
                     help="fuse every K-th pixel of each depth frame in both directions (default 1: all)")
    _add_acting_options(act)
    act.set_defaults(func=cmd_act)

    report = commands.add_parser("report", help="a table of finished policy runs: success over seeds, reliance")
    report.add_argument("runs", nargs="+", metavar="RUN", help="run directories of d2a train-policy (or policy.pt)")
    report.add_argument("--plot", metavar="PNG", help="also draw the rows as bars per task (seeds as dots)")
    report.set_defaults(func=cmd_report)

    data = commands.add_parser("data", help="data sets").add_subparsers(dest="what", required=True)
    data_info = data.add_parser("info", help="episodes, lengths, success, point counts, size on disk")
    data_info.add_argument("dir")
    data_info.set_defaults(func=cmd_data_info)
    data_import = data.add_parser("import", help="a DP3 / MP1 zarr, a LeRobot data set or a recording of real "
                                                 "episodes into a data set")
    source = data_import.add_mutually_exclusive_group(required=True)
    source.add_argument("--dp3", metavar="ZARR", help="a DP3 / MP1 zarr (data/point_cloud, state, action, "
                                                     "meta/episode_ends)")
    source.add_argument("--recording", metavar="DIR", help="a recording (collectors/recording.py): its frames are "
                                                         "fused into clouds with --crop-box and --num-points")
    source.add_argument("--lerobot", metavar="DIR", help="a LeRobot data set (format v2.x or v3.0) with a point-cloud "
                                                        "feature, or a depth array fused with --camera")
    data_import.add_argument("--out", required=True, help="data set directory to create")
    data_import.add_argument("--overwrite", action="store_true", help="replace an existing data set")
    data_import.add_argument("--task", default=None, help="the task a DP3 zarr's or a LeRobot data set's episodes "
                                                          "show (see `d2a tasks`)")
    _add_cloud_options(data_import)  # the env options whose clouds match the file's
    lerobot = data_import.add_argument_group("LeRobot data sets (--lerobot)")
    lerobot.add_argument("--cloud-key", default=None, help="the point-cloud feature, (P, 3) or (P, 6) "
                                                           "(default: observation.point_cloud or .pointcloud)")
    lerobot.add_argument("--camera", metavar="JSON", default=None,
                         help="fuse a depth feature instead: a file with the camera's intrinsics {fx, fy, cx, cy} "
                              "and its 4x4 camera-to-base pose (OpenCV axes); --crop-box and --num-points apply")
    lerobot.add_argument("--depth-key", default=None, help="the depth feature, (H, W) (default: observation.depth)")
    lerobot.add_argument("--depth-scale", type=_finite_at_least(1e-6), default=1.0,
                         help="metres per depth unit (0.001: millimetres; default 1)")
    lerobot.add_argument("--state-key", default="observation.state", help="the feature read as agent_pos")
    lerobot.add_argument("--full-state-key", default=None, help="the feature read as state (default: --state-key's)")
    data_import.set_defaults(func=cmd_data_import)
    data_export = data.add_parser("export", help="a data set here as a DP3 / MP1 zarr")
    data_export.add_argument("dir", help="data set directory (d2a collect)")
    data_export.add_argument("--dp3", required=True, metavar="ZARR", help="the zarr directory to write")
    data_export.add_argument("--overwrite", action="store_true", help="replace an existing zarr")
    data_export.set_defaults(func=cmd_data_export)

    bench_experts = bench.add_parser("experts", help="expert success per task (Meta-World, Adroit), parallel speed-up")
    bench_experts.add_argument("--task", action="append", default=None, help="default: all 50 Meta-World tasks")
    bench_experts.add_argument("--episodes", type=POSITIVE, default=None)
    bench_experts.add_argument("--workers", type=POSITIVE, default=None)
    bench_experts.add_argument("--imitation-demos", type=NON_NEGATIVE, default=None,
                               help="the learnability check: mp1-state trained on this many demonstrations (0: off)")
    bench_experts.add_argument("--imitation-algo", choices=STATE_ALGOS, default=None,
                               help="the check's state policy (default mp1-state; dp3-state: the diffusion expert)")
    bench_experts.add_argument("--imitation-episodes", type=POSITIVE, default=None,
                               help="its evaluation episodes on new layouts (default 100)")
    bench_experts.add_argument("--imitation-dart-noise", type=NON_NEGATIVE_FLOAT, default=None, metavar="STD",
                               help="collect the check's demonstrations with DART noise (d2a collect --dart-noise)")
    bench_experts.add_argument("--imitation-action-draws", type=POSITIVE, default=None, metavar="K",
                               help="its policy acts on the mean of K chunks per plan (d2a eval --action-draws)")
    bench_experts.add_argument("--workdir", default=None, help="the check's data and policies")
    _add_ray_option(bench_experts)
    bench_experts.set_defaults(func=cmd_bench_experts)

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

    bench_latency = bench.add_parser("latency", help="batch-1 CPU latency: MeanFlow 1 NFE vs DDIM 10 NFE, imagination")
    bench_latency.add_argument("--task", default=None)
    bench_latency.add_argument("--num-points", type=POSITIVE, default=None)
    bench_latency.add_argument("--repeats", type=POSITIVE, default=None)
    bench_latency.add_argument("--world-model", help="also time this trained world model (needs --data)")
    bench_latency.add_argument("--data", help="demonstrations to imagine from, with their recorded actions")
    bench_latency.set_defaults(func=cmd_bench_latency)

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

    bench_fusion = bench.add_parser("fusion", help="two 640x480 depth frames fused to 1024 points: ms on one thread")
    bench_fusion.add_argument("--repeats", type=POSITIVE, default=None)
    bench_fusion.set_defaults(func=cmd_bench_fusion)

    bench_change = bench.add_parser("change", help="how close the imagined change, the observed change and the "
                                                   "present cloud come to where the scene will change")
    bench_change.add_argument("--world-model", required=True, help="checkpoint of d2a train-wm")
    bench_change.add_argument("--data", required=True, help="its demonstrations")
    bench_change.add_argument("--demos", type=POSITIVE, default=None,
                              help="the world model trained on the first N of each task: measure on the rest "
                                   "(default: its own held-out episodes)")
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
    bench_success.add_argument("--steps", type=POSITIVE, default=None, help="policy training steps (default: preset's)")
    _add_policy_options(bench_success)
    bench_success.add_argument("--evaluations", type=POSITIVE, default=None,
                               help="periodic evaluations during training, the last at the final step; the paper "
                                    "protocol averages the best 5 (default: the preset's, cpu 5, paper 15)")
    _add_eval_layouts_option(bench_success)
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
    bench_success.add_argument("--wm-rollouts", type=NON_NEGATIVE, default=None,
                               help="noisy expert rollouts per task the world model also trains on (default 0)")
    bench_success.add_argument("--rollout-noise", type=NON_NEGATIVE_FLOAT, default=None,
                               help="std of their action noise (default 0.3)")
    bench_success.add_argument("--dart-noise", type=NON_NEGATIVE_FLOAT, default=None, metavar="STD",
                               help="collect the demonstrations with DART noise (d2a collect --dart-noise); their "
                                    "data, world models and cells are named apart")
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
    _add_ray_option(bench_success)
    bench_success.set_defaults(func=cmd_bench_success)

    bench_table1 = bench.add_parser(
        "table1", help="the paper's Table I: Meta-World groups and Adroit x methods x seeds, resumable; "
                       "per-group table beside the paper's rows, CSV, plot")
    bench_table1.add_argument("--group", action="append", choices=("very_hard", "hard", "medium", "easy", "adroit"),
                              default=None, help="repeat for several (default: very_hard hard medium easy adroit, in "
                                                 "order; adroit: the three Adroit columns, at their own settings)")
    bench_table1.add_argument("--algo", action="append", choices=ALGOS, default=None, help="default: mp1 dp3")
    _add_grid_options(bench_table1, "docs/table1", "outputs/table1")
    bench_table1.set_defaults(func=cmd_bench_table1)

    bench_table4 = bench.add_parser("table4", help="the paper's Table IV: success against 1-20 demonstrations on "
                                                   "its four tasks, resumable; the paper's layout, CSV, plot")
    bench_table4.add_argument("--task", action="append", default=None,
                              help="default: lever-pull assembly push stick-pull")
    bench_table4.add_argument("--demos", type=POSITIVE, action="append", default=None,
                              help="demonstration count; repeat (default 5 1 2 10 20, in order)")
    bench_table4.add_argument("--algo", action="append", choices=ALGOS, default=None,
                              help="default: mp1 d2a d2a-present")
    _add_grid_options(bench_table4, "docs/table4", "outputs/table4")
    bench_table4.set_defaults(func=cmd_bench_table4)

    bench_paired = bench.add_parser("paired", help="one method against another on the cells they share (same task, "
                                                   "seed, settings, layouts): per pair and over pairs, intervals")
    bench_paired.add_argument("--results", action="append", required=True,
                              help="a directory of cells, or a grid's results holding cells/ (repeatable)")
    bench_paired.add_argument("--algo", choices=ALGOS, default=None, help="default: d2a")
    bench_paired.add_argument("--control", choices=ALGOS, default=None, help="default: d2a-present")
    bench_paired.add_argument("--plot", default=None, help="a PNG of the per-pair differences (default: none)")
    bench_paired.set_defaults(func=cmd_bench_paired)

    bench_ray = bench.add_parser("ray", help="the same small bench success grid on 1 and 2 Ray CPUs: wall time")
    bench_ray.add_argument("--task", default=None, help="default: reach")
    bench_ray.add_argument("--algo", choices=ALGOS, default=None, help="default: mp1")
    bench_ray.add_argument("--seed", type=NON_NEGATIVE, action="append", default=None, help="cells (default 0-3)")
    bench_ray.add_argument("--cpus", type=POSITIVE, action="append", default=None, help="Ray CPUs (default 1, 2)")
    bench_ray.add_argument("--steps", type=POSITIVE, default=None, help="policy training steps (default 300)")
    bench_ray.add_argument("--workdir", default=None)
    bench_ray.set_defaults(func=cmd_bench_ray)

    demo = commands.add_parser("demo", help="end to end on Hammer: collect, world model, D2A policy, evaluate")
    demo.add_argument("--task", default=None, help="default: hammer")
    demo.add_argument("--out", default=None, help="output directory (default: outputs/demo)")
    demo.add_argument("--episodes", type=POSITIVE, default=None, help="demonstrations (default 10)")
    demo.add_argument("--wm-steps", type=POSITIVE, default=None)
    demo.add_argument("--policy-steps", type=POSITIVE, default=None)
    demo.add_argument("--eval-episodes", type=POSITIVE, default=None)
    demo.add_argument("--seed", type=NON_NEGATIVE, default=None)
    demo.add_argument("--threads", type=POSITIVE, default=None,
                      help="torch threads of the trainings (default: torch's own; 1 beside other busy work)")
    demo.set_defaults(func=cmd_demo)
    return parser


def main(argv: Sequence[str] | None = None) -> None:
    import d2a_envs  # noqa: F401  (chooses MuJoCo's GL platform before anything imports mujoco)

    args = build_parser().parse_args(argv)
    try:
        args.func(args)
    except (ValueError, FloatingPointError, JobsLost) as error:  # bad input, a diverged run, Ray workers lost
        sys.exit(f"d2a: error: {error}")
    except ImportError as error:
        if error.name != "ray":  # an optional dependency the command asked for; anything else is a bug
            raise
        sys.exit(f"d2a: error: {error}")


if __name__ == "__main__":
    main()
