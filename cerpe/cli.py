"""``cerpe`` command line: one subcommand per pipeline step.

Every subcommand lives in its own module exposing ``add_arguments(parser)`` and
``main(args) -> int``; modules keep heavy imports (torch, models) inside
functions so that ``cerpe --help`` is instant. Deliberate errors
(:class:`cerpe.errors.CerpeError`) are printed as one line, exit code 2.
"""
from __future__ import annotations

import argparse
import importlib
import logging
import sys

from .errors import CerpeError

# name -> (module, one-line help). Add a line here to add a subcommand.
SUBCOMMANDS: dict[str, tuple[str, str]] = {}


def _register(name: str, module: str, help_: str) -> None:
    SUBCOMMANDS[name] = (module, help_)


_register("synth", "cerpe.synth.cli", "render a synthetic encounter world to a mocap-style dataset")
_register("check", "cerpe.datasets.cli", "validate a dataset manifest, load it and summarise it")
_register("run", "cerpe.pipeline.run", "run a method (cerpe, cerpe-wo-em, baselines) on a manifest")
_register("eval", "cerpe.pipeline.evaluate", "compute the paper's metrics for a run folder")
_register("bench", "cerpe.pipeline.bench", "benchmark per-stage latency, memory and bytes")
_register("paper", "cerpe.pipeline.paper", "build every table and figure (what `make paper` runs)")
_register("online", "cerpe.online.cli", "run ONE robot of a team online, talking to its peers over Zenoh")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cerpe",
        description=(
            "CERPE: communication-efficient multi-robot relative pose estimation.\n"
            "Robots broadcast a fixed-size descriptor and their odometry pose; descriptor\n"
            "similarity gates raw-image requests; a multi-view backbone over a bounded\n"
            "keyframe memory gives ego-motion and direct inter-robot poses; metric depth\n"
            "fixes the scale; without overlap the last direct pose is propagated."
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Run `cerpe COMMAND --help` for the options of one command.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_) in SUBCOMMANDS.items():
        try:
            mod = importlib.import_module(module)
        except ModuleNotFoundError as exc:
            if exc.name and exc.name.startswith("cerpe"):
                continue  # subcommand not built in this checkout
            raise
        p = sub.add_parser(name, help=help_, description=(mod.__doc__ or help_).strip(),
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        mod.add_arguments(p)
        p.set_defaults(_main=mod.main)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=[logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)] if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )
    if not getattr(args, "_main", None):
        parser.print_help()
        return 2
    try:
        return int(args._main(args) or 0)
    except CerpeError as exc:
        print(f"cerpe {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"cerpe {args.command}: interrupted; rerun the same command to resume", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
