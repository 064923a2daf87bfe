"""The ``d2a`` command: one entry point, one subcommand per job."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from collectors.ray_jobs import JobsLost  # the standard library only: `d2a --help` stays fast
from d2a.bench_cli import add_bench_commands
from d2a.cli_options import (
    ALGOS,
    DEMOS_HELP,
    EXPERT_KINDS,
    NON_NEGATIVE,
    NON_NEGATIVE_FLOAT,
    POSITIVE,
    add_acting_options,
    add_cloud_options,
    add_env_options,
    add_eval_layouts_option,
    add_policy_options,
    add_ray_option,
    finite_at_least,
    parsed_acting,
    parsed_env_kwargs,
    parsed_stacked_horizons,
    replace_given,
)


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

    path = plot_task_point_cloud(args.task, args.out, seed=args.seed, steps=args.steps, **parsed_env_kwargs(args))
    print(f"wrote {path}")


def _policy_rollouts(args: argparse.Namespace) -> dict[str, object]:
    """``d2a collect --policy``: the checkpoint acts, its own actions stored, in the env settings
    of the data it trained on (so the rollouts can join that data set)."""
    from d2a_agents.policy.checkpoints import checkpoint_student, trained_env_kwargs

    if len(args.task) != 1:
        raise ValueError("--policy collects one task's rollouts: give one --task")
    if parsed_env_kwargs(args) or args.max_episode_steps is not None:
        raise ValueError("--policy collects in the env settings its policy trained with: drop the env options")
    stored = trained_env_kwargs(args.policy, args.task[0])
    return dict(student=checkpoint_student(args.policy, args.task[0]), student_labels=False,
                max_episode_steps=stored.pop("max_episode_steps", None), env_kwargs=stored)


def cmd_collect(args: argparse.Namespace) -> None:
    from collectors.collect import CollectConfig, collect

    config = replace_given(
        CollectConfig(tasks=tuple(args.task), out=args.out, env_kwargs=parsed_env_kwargs(args), append=args.append,
                      overwrite=args.overwrite, ray_address=args.ray),
        episodes=args.episodes, seed=args.seed, max_attempts_factor=args.max_attempts_factor,
        max_episode_steps=args.max_episode_steps, action_noise=args.action_noise,
        keep_failures=True if args.keep_failures else None, expert=args.expert, dart_noise=args.dart_noise,
    )
    if args.policy is not None:
        config = replace_given(config, **_policy_rollouts(args))
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
        dataset = import_dp3(args.dp3, args.out, args.task, parsed_env_kwargs(args) or None, overwrite=args.overwrite)
    elif args.lerobot:
        import d2a_envs
        from collectors.lerobot_format import import_lerobot

        if args.task is None:
            raise ValueError("--lerobot needs --task: the task its episodes show")
        suite = d2a_envs.task_config(args.task)
        dataset = import_lerobot(
            args.lerobot, args.out, args.task, cloud_key=args.cloud_key, depth_key=args.depth_key, camera=args.camera,
            depth_scale=args.depth_scale, crop_box=args.crop_box or suite.crop_box,
            num_points=args.num_points or suite.num_points, state_key=args.state_key,
            full_state_key=args.full_state_key, env_kwargs=parsed_env_kwargs(args) or None, overwrite=args.overwrite)
    else:
        import json

        import d2a_envs
        from collectors.recording import import_recording

        task = json.loads((Path(args.recording) / "recording.json").read_text())["task"]
        suite = d2a_envs.task_config(task)
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
                             acting=parsed_acting(args), **rate).run(args.steps)
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
    model = replace_given(base, horizon=args.horizon, action_history=args.history, channels=args.channels,
                           feature_mode=args.feature_mode, plane_pooling=args.plane_pooling, encoder=args.encoder,
                           reads_actions=False if args.without_actions else None,
                           resolution=tuple(args.resolution) if args.resolution else None)
    config = replace_given(
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
    path = plot_task_imagination(args.world_model, args.task, args.out, args.seed, steps, **parsed_env_kwargs(args))
    print(f"wrote {path}")


def cmd_train_policy(args: argparse.Namespace) -> None:
    from d2a_agents.policy.train import POLICY_PRESETS, TrainPolicyConfig, train_policy

    preset = replace_given(POLICY_PRESETS[args.preset], steps=args.steps, batch_size=args.batch_size,
                            image_batch_size=args.batch_size, learning_rate=args.lr, image_learning_rate=args.lr,
                            trim_after_success=args.trim_after_success)
    policy = replace_given(preset.policy, algo=args.algo, horizon=args.horizon, n_obs_steps=args.n_obs_steps,
                            n_action_steps=args.n_action_steps, num_points=args.policy_points,
                            imagined_points=args.imagined_points, oracle_horizon=args.oracle_horizon,
                            stacked_horizons=parsed_stacked_horizons(args), cfg_similarity=args.cfg_similarity,
                            adaptive_power=args.adaptive_power, cfg_guidance=args.cfg_guidance,
                            cfg_scale=args.cfg_scale, meanflow_output=args.meanflow_output,
                            cfg_thresholds=tuple(args.cfg_thresholds) if args.cfg_thresholds else None)
    config = replace_given(
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
    env_kwargs = parsed_env_kwargs(args)
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
                                     acting=parsed_acting(args))
    print(result.summary())


def cmd_demo(args: argparse.Namespace) -> None:
    from d2a.demo import DemoConfig, run_demo

    base = DemoConfig()
    run_demo(replace_given(
        base, task=args.task, out=args.out, episodes=args.episodes, world_model_steps=args.wm_steps,
        policy=replace_given(base.policy, steps=args.policy_steps), eval_episodes=args.eval_episodes,
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
    add_env_options(pointcloud)
    pointcloud.add_argument("--steps", type=NON_NEGATIVE, default=0, help="random steps before the picture")
    pointcloud.add_argument("--out", required=True)
    pointcloud.set_defaults(func=cmd_viz_pointcloud)

    imagine = viz.add_parser("imagine", help="current, imagined and true future clouds over an episode")
    add_env_options(imagine)
    imagine.add_argument("--world-model", required=True, help="checkpoint of d2a train-wm")
    imagine.add_argument("--steps", default="10,40,70,100,130", help="comma-separated control steps to draw")
    imagine.add_argument("--out", required=True)
    imagine.set_defaults(func=cmd_viz_imagine)

    add_bench_commands(commands)

    collect = commands.add_parser("collect", help="expert demonstrations (scripted, controller or planner) into a "
                                                  "data set")
    add_env_options(collect, several_tasks=True)
    collect.add_argument("--episodes", type=POSITIVE, default=None, help="successful episodes to keep per task")
    collect.add_argument("--out", required=True, help="data set directory")
    collect.add_argument("--max-attempts-factor", type=POSITIVE, default=None, help="give up after episodes x this "
                         "(default 3; 10 with --dart-noise, whose perturbed expert fails more often)")
    collect.add_argument("--max-episode-steps", type=POSITIVE, default=None)
    collect.add_argument("--action-noise", type=NON_NEGATIVE_FLOAT, default=None, metavar="STD",
                         help="Gaussian noise added to the expert's actions: rollouts for a world model, never "
                              "trained on by policies (with --keep-failures)")
    collect.add_argument("--keep-failures", action="store_true", help="store every attempt, not only successes")
    collect.add_argument("--policy", default=None, metavar="RUN",
                         help="a policy checkpoint (or run directory) acts instead of the expert and its own actions "
                              "are stored, every attempt kept: rollouts of the policy, in the env settings it trained "
                              "with (one --task; --episodes counts attempts)")
    collect.add_argument("--dart-noise", type=NON_NEGATIVE_FLOAT, default=None, metavar="STD",
                         help="Gaussian noise on the executed actions while the stored labels stay the expert's "
                              "(DART): demonstrations that also show how the expert recovers")
    collect.add_argument("--expert", choices=EXPERT_KINDS, default=None,
                         help="Adroit: the controller (Door, Hammer: state feedback, their default; Pen: its "
                              "sequence library) or the predictive-sampling planner (Pen's default)")
    mode = collect.add_mutually_exclusive_group()
    mode.add_argument("--append", action="store_true", help="add to (or resume) an existing data set")
    mode.add_argument("--overwrite", action="store_true", help="replace an existing data set")
    add_ray_option(collect)
    collect.set_defaults(func=cmd_collect)

    train_wm = commands.add_parser("train-wm", help="train the triplane world model on a data set")
    train_wm.add_argument("--data", required=True, help="data set directory (d2a collect)")
    train_wm.add_argument("--out", required=True, help="checkpoint file; an existing one is resumed")
    train_wm.add_argument("--preset", choices=("cpu", "paper"), default="cpu",
                          help="cpu: 128x128x32, point-scatter encoder; paper: 128x128x32, Conv3d encoder (GPU work)")
    train_wm.add_argument("--resolution", type=POSITIVE, nargs=3, default=None, metavar=("X", "Y", "Z"))
    train_wm.add_argument("--horizon", type=POSITIVE, default=None, help="H, steps imagined ahead")
    train_wm.add_argument("--history", type=POSITIVE, default=None, help="past actions conditioning the model")
    train_wm.add_argument("--without-actions", action="store_true",
                          help="read no past actions (zeros): imagine from the scene alone")
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
    add_policy_options(train_policy)
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
    add_eval_layouts_option(train_policy)
    train_policy.add_argument("--workers", type=POSITIVE, default=None)
    train_policy.add_argument("--seed", type=NON_NEGATIVE, default=None)
    train_policy.set_defaults(func=cmd_train_policy)

    evaluation = commands.add_parser("eval", help="evaluate a policy checkpoint (or the task's expert)")
    add_env_options(evaluation)
    evaluation.add_argument("--policy", required=True, help="policy.pt of d2a train-policy, or 'expert'")
    evaluation.add_argument("--expert", choices=EXPERT_KINDS, default=None,
                            help="with --policy expert on Adroit: the controller (Door's and Hammer's default) "
                                 "or the planner (Pen's)")
    evaluation.add_argument("--episodes", type=POSITIVE, default=100)
    evaluation.add_argument("--workers", type=POSITIVE, default=2)
    evaluation.add_argument("--end-on-success", action="store_true",
                            help="end episodes at their first success (same success rate, faster; returns stop there)")
    add_acting_options(evaluation)
    add_ray_option(evaluation)
    evaluation.set_defaults(func=cmd_eval)

    act = commands.add_parser("act", help="run a checkpoint at a fixed control rate on a robot (here the simulated "
                                          "one; your own through d2a_agents.deploy's interfaces); Ctrl-C stops")
    act.add_argument("--policy", required=True, help="policy.pt of d2a train-policy (or its run directory)")
    act.add_argument("--task", default=None, help="default: the policy's first task")
    act.add_argument("--steps", type=POSITIVE, default=None, help="control steps (default: until Ctrl-C)")
    act.add_argument("--hz", type=finite_at_least(0.001), default=None, help="control rate (default 10)")
    act.add_argument("--seed", type=NON_NEGATIVE, default=0, help="the simulated scene's layout")
    act.add_argument("--pixel-stride", type=POSITIVE, default=1, metavar="K",
                     help="fuse every K-th pixel of each depth frame in both directions (default 1: all)")
    add_acting_options(act)
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
    add_cloud_options(data_import)  # the env options whose clouds match the file's
    lerobot = data_import.add_argument_group("LeRobot data sets (--lerobot)")
    lerobot.add_argument("--cloud-key", default=None, help="the point-cloud feature, (P, 3) or (P, 6) "
                                                           "(default: observation.point_cloud or .pointcloud)")
    lerobot.add_argument("--camera", metavar="JSON", default=None,
                         help="fuse a depth feature instead: a file with the camera's intrinsics {fx, fy, cx, cy} "
                              "and its 4x4 camera-to-base pose (OpenCV axes); --crop-box and --num-points apply")
    lerobot.add_argument("--depth-key", default=None, help="the depth feature, (H, W) (default: observation.depth)")
    lerobot.add_argument("--depth-scale", type=finite_at_least(1e-6), default=1.0,
                         help="metres per depth unit (0.001: millimetres; default 1)")
    lerobot.add_argument("--state-key", default="observation.state", help="the feature read as agent_pos")
    lerobot.add_argument("--full-state-key", default=None, help="the feature read as state (default: --state-key's)")
    data_import.set_defaults(func=cmd_data_import)
    data_export = data.add_parser("export", help="a data set here as a DP3 / MP1 zarr")
    data_export.add_argument("dir", help="data set directory (d2a collect)")
    data_export.add_argument("--dp3", required=True, metavar="ZARR", help="the zarr directory to write")
    data_export.add_argument("--overwrite", action="store_true", help="replace an existing zarr")
    data_export.set_defaults(func=cmd_data_export)

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
