"""The ``d2a`` command's shared pieces: argument types checked at the command line, the option
groups several subcommands take, and what turns the parsed options into settings.

Only the standard library is imported here: ``d2a --help`` stays fast.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from d2a_agents.policy.checkpoints import Acting

# d2a_agents.policy.agent.ALGORITHMS, spelled out so that `d2a --help` does not import torch
ALGOS = ("d2a", "d2a-change", "d2a-change-top", "d2a-no-cfg", "d2a-no-imagination", "d2a-present", "d2a-oracle",
         "mp1", "dp3", "flowpolicy", "edm", "cp", "dp", "mp1-state", "dp3-state")
STATE_ALGOS = tuple(algo for algo in ALGOS if algo.endswith("-state"))  # the privileged-state references
EVAL_LAYOUTS = ("fixed", "fresh")  # d2a_agents.policy.train.EVAL_LAYOUTS, likewise
EXPERT_KINDS = ("controller", "planner")  # collectors.adroit_experts.EXPERT_KINDS, likewise


def parse_box(text: str | None) -> tuple[tuple[float, ...], tuple[float, ...]] | None:
    """An argparse type: a crop box ``x0,y0,z0,x1,y1,z1`` as its (low, high) corners."""
    if text is None:
        return None
    values = [float(v) for v in text.split(",")]
    if len(values) != 6:
        raise argparse.ArgumentTypeError("crop box must be six numbers: x0,y0,z0,x1,y1,z1")
    return tuple(values[:3]), tuple(values[3:])


def int_at_least(minimum: int) -> Callable[[str], int]:
    """An argparse type: an integer >= ``minimum``, refused at the command line before any work."""

    def integer(text: str) -> int:
        value = int(text)  # a ValueError becomes argparse's "invalid integer value"
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be at least {minimum}, got {value}")
        return value

    return integer


def finite_at_least(minimum: float) -> Callable[[str], float]:
    """An argparse type: a finite number >= ``minimum`` (nan and inf refused)."""

    def number(text: str) -> float:
        value = float(text)
        if not minimum <= value < float("inf"):
            raise argparse.ArgumentTypeError(f"must be a finite number >= {minimum:g}, got {text}")
        return value

    return number


POSITIVE, NON_NEGATIVE = int_at_least(1), int_at_least(0)
NON_NEGATIVE_FLOAT = finite_at_least(0.0)


DEMOS_HELP = "train on the first N episodes of each task (default: all); runs on 1, 2, 5 ... of one data set nest"


def add_env_options(parser: argparse.ArgumentParser, several_tasks: bool = False) -> None:
    """The task (one, or repeatable), the seed and the env's own options."""
    if several_tasks:
        parser.add_argument("--task", action="append", required=True, help="task name or env id; repeat for several")
    else:
        parser.add_argument("--task", default="hammer", help="task name or env id (see `d2a tasks`)")
    parser.add_argument("--seed", type=NON_NEGATIVE, default=0)
    parser.add_argument("--action-repeat", type=POSITIVE, default=None,
                        help="hold each action for this many simulator steps (DP3's Adroit envs: 2; default 1)")
    add_cloud_options(parser)


def add_cloud_options(parser: argparse.ArgumentParser) -> None:
    """The env options that shape its clouds (read back by ``parsed_env_kwargs``)."""
    parser.add_argument("--backend", choices=("raycast", "render"), default=None)
    parser.add_argument("--cameras", default=None, help="comma-separated camera names, fused in the world frame")
    parser.add_argument("--image-size", type=POSITIVE, default=None)
    parser.add_argument("--num-points", type=POSITIVE, default=None)
    parser.add_argument("--crop-box", type=parse_box, default=None, help="x0,y0,z0,x1,y1,z1 in metres")
    parser.add_argument("--hide-sites", action="store_true", help="leave MuJoCo sites (goal markers) out")
    parser.add_argument("--rgb-image-size", type=POSITIVE, default=None, metavar="PIXELS",
                        help="add the first camera's colour image (PIXELS a side) to the observations: what "
                             "--algo dp reads (stored per step by d2a collect; lit with --backend render)")


def add_ray_option(parser: argparse.ArgumentParser) -> None:
    """``--ray [ADDRESS]``: run the work as Ray jobs."""
    parser.add_argument("--ray", nargs="?", const="local", default=None, metavar="ADDRESS",
                        help="run the episodes (or cells) as Ray jobs: alone, on a Ray instance started on this "
                             "machine; 'auto': the running cluster; or a cluster address (needs the ray extra)")


def add_acting_options(parser: argparse.ArgumentParser) -> None:
    """How a checkpoint acts (``Acting``): actions per planned chunk, draws per chunk."""
    parser.add_argument("--n-action-steps", type=POSITIVE, default=None,
                        help="actions executed per planned chunk before planning again (default: the "
                             "checkpoint's; 1 plans after every action)")
    parser.add_argument("--action-draws", type=POSITIVE, default=1, metavar="K",
                        help="chunks drawn from independent noise per plan, acted on as their mean (default 1)")
    parser.add_argument("--sample-steps", type=POSITIVE, default=None, metavar="K",
                        help="network evaluations per drawn chunk (default: the expert's own; one for mp1, "
                             "d2a, flowpolicy, cp)")


def parsed_acting(args: argparse.Namespace) -> Acting:
    """The ``Acting`` that :func:`add_acting_options` read."""
    from d2a_agents.policy.checkpoints import Acting

    return Acting(args.n_action_steps, args.action_draws, args.sample_steps)


def add_eval_layouts_option(parser: argparse.ArgumentParser) -> None:
    """Whether periodic evaluations replay the same layouts or draw new ones."""
    parser.add_argument("--eval-layouts", choices=EVAL_LAYOUTS, default=None,
                        help="fixed: every periodic evaluation on the same layouts (default); fresh: new layouts "
                             "at each, as DP3's and MP1's runners (the paper protocol's best 5 then also "
                             "select over layout draws)")


def add_policy_options(parser: argparse.ArgumentParser) -> None:
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


def with_policy_options(bench: Any, args: argparse.Namespace) -> Any:
    """A success bench's per-cell settings with the policy options given (steps, point budget,
    oracle horizons, MeanFlow output)."""
    policy = replace_given(bench.policy.policy, num_points=args.policy_points, imagined_points=args.imagined_points,
                            oracle_horizon=args.oracle_horizon, stacked_horizons=parsed_stacked_horizons(args),
                            meanflow_output=args.meanflow_output)
    return dataclasses.replace(bench, policy=replace_given(bench.policy, steps=args.steps, policy=policy))


def parsed_stacked_horizons(args: argparse.Namespace) -> tuple[int, ...] | None:
    """The ``--stacked-horizon`` values as the policy setting (``None``: not given)."""
    return tuple(args.stacked_horizons) if args.stacked_horizons else None


def replace_given(instance: Any, **changes: object) -> Any:
    """``dataclasses.replace`` with the options the user gave (``None``: keep the default)."""
    return dataclasses.replace(instance, **{k: v for k, v in changes.items() if v is not None})


def parsed_env_kwargs(args: argparse.Namespace) -> dict[str, object]:
    """The env keyword arguments of the options given (those not given are left out)."""
    kwargs = dict(backend=args.backend, image_size=args.image_size, num_points=args.num_points, crop_box=args.crop_box,
                  rgb_image_size=args.rgb_image_size,
                  action_repeat=getattr(args, "action_repeat", None))  # an env option; data import has none
    if args.cameras:
        kwargs["cameras"] = tuple(args.cameras.split(","))
    if args.hide_sites:
        kwargs["show_sites"] = False
    return {k: v for k, v in kwargs.items() if v is not None}
