"""`cosim encoder train`: build the frozen perception encoder (eval/training/encoder.py) from
the project's own simulator; ``cosim train --encoder FILE`` and ``cosim test --encoder FILE``
use it (docs/task.md, "The frozen perception encoder"). The parser is declared here and added
to `cosim`'s in eval/cli/__init__.py."""

from __future__ import annotations

import sys
from pathlib import Path


def add_parser(sub, formatter_class=None) -> None:
    """Add ``encoder`` (with its one action, ``train``) to `cosim`'s subcommands ``sub``, its
    parsers formatted by ``formatter_class`` (`cosim`'s)."""
    from eval.labels import ENVS
    from eval.training.encoder import MAX_SEED, camera_variants
    from eval.training.options import int_in, names_text

    how = {"formatter_class": formatter_class} if formatter_class is not None else {}
    enc = sub.add_parser("encoder", help="build the frozen perception encoder that --encoder trains and tests on",
                         **how)
    actions = enc.add_subparsers(metavar="ACTION")
    t = actions.add_parser(
        "train", help="collect labelled camera frames from the simulator and train the encoder on them",
        description="Drive every AC of each environment with the autopilot and perturbations (action noise, held "
                    "random excursions), keep each AC's camera frame and its state-track vector (65 numbers: "
                    "lane and route geometry, speed, signal, nearest cars and pedestrians), and train the Nature "
                    "CNN to predict them; report the held-out error per group against predicting the mean "
                    "(docs/task.md, The frozen perception encoder).", **how)
    t.add_argument("--out", type=Path, required=True, metavar="FILE", help="the encoder file to write (required, no default)")
    t.add_argument("--frames", type=int_in(2), default=40_000, metavar="N",
                   help="labelled frames in all, an equal share per environment (uint8: 21 kB each)")
    t.add_argument("--epochs", type=int_in(1), default=5, metavar="E", help="passes over the training frames")
    t.add_argument("--seed", type=int_in(0, MAX_SEED), default=0, metavar="S",
                   help="seed of the episodes, perturbations, weights and minibatches")
    t.add_argument("--envs", nargs="+", default=list(ENVS), metavar="ENV",
                   help=f"environments the frames come from: {names_text(ENVS)} or scenario .yaml files")
    t.add_argument("--agents", type=int_in(1, 6), default=None, metavar="N",
                   help="ACs per environment (default: every spawn point)")
    t.add_argument("--obs", choices=camera_variants(), default="image",
                   help="the camera variant of the frames (runs with --encoder must observe the same)")
    t.add_argument("--horizon", type=int_in(1), default=200, metavar="STEPS", help="steps per collection episode")
    t.add_argument("--held-out", type=float, default=0.1, metavar="F",
                   help="share of each environment's frames from held-out episodes, for the error report")
    t.add_argument("--batch-size", type=int_in(1), default=128, metavar="B", help="frames per gradient step")
    t.add_argument("--lr", type=float, default=5e-4, help="Adam's learning rate")
    t.add_argument("--torch-threads", type=int_in(0), default=0, metavar="K",
                   help="torch threads for the training (0: torch's default, the CPUs)")
    t.add_argument("--data", type=Path, default=None, metavar="NPZ",
                   help="keep the collected frames in this .npz, or train on it when it exists (default: none)")
    t.add_argument("--quiet", action="store_true", help="no progress bars")
    t.set_defaults(func=cmd_train)
    enc.set_defaults(func=lambda args: enc.print_help() or 2)


def cmd_train(args) -> int:
    """Run `cosim encoder train`; print the summary and the held-out error table."""
    from eval.training.config import TrainError
    from eval.training.encoder import build

    if not 0.0 <= args.held_out < 1.0:
        print(f"cosim encoder train: error: --held-out must be in [0, 1), got {args.held_out}", file=sys.stderr)
        return 2
    if args.torch_threads:
        import torch

        torch.set_num_threads(args.torch_threads)
    try:
        info = build(args.out, frames=args.frames, epochs=args.epochs, seed=args.seed, envs=args.envs,
                     agents=args.agents, obs=args.obs, horizon=args.horizon, held_out=args.held_out,
                     batch_size=args.batch_size, lr=args.lr, data=args.data, progress=not args.quiet,
                     command=" ".join(["cosim", *sys.argv[1:]]))
    except TrainError as exc:
        print(f"cosim encoder train: error: {exc}", file=sys.stderr)
        return 2
    print(summary(info, args.out))
    return 0


def summary(info: dict, out: Path) -> str:
    """The lines `cosim encoder train` prints: the file, its hash, sizes, times and the
    held-out error per group (normalised MSE, the mean's, their ratio)."""
    lines = [f"encoder: {out} (sha256 {info['sha256']})",
             f"frames: {info['frames']} ({info['train_frames']} training, {info['held_out_frames']} held out) from "
             f"{' '.join(info['envs'])}; data {info['data_bytes'] / 1e6:.0f} MB",
             f"time: {info['collect_seconds']:.0f} s collecting, {info['train_seconds']:.0f} s training "
             f"({info['epochs']} epochs; loss per epoch {info['train_loss']})"]
    errors = info.get("held_out_error") or {}
    if errors:
        lines.append("held-out error (MSE of normalised labels; mean = predicting the training mean):")
        lines.append(f"  {'group':<12} {'encoder':>8} {'mean':>8} {'ratio':>6}")
        for group, e in errors.items():
            ratio = f"{e['ratio']:>6.2f}" if e["ratio"] == e["ratio"] else f"{'-':>6}"  # NaN: nothing varies
            lines.append(f"  {group:<12} {e['mse']:>8.3f} {e['baseline']:>8.3f} {ratio}")
    return "\n".join(lines)


__all__ = ["add_parser", "cmd_train", "summary"]
