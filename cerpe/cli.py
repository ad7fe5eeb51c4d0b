"""``cerpe`` command line: one subcommand per pipeline step.

Every subcommand lives in its own module exposing ``add_arguments(parser)`` and
``main(args) -> int``; modules keep heavy imports (torch, models) inside
functions so that ``cerpe --help`` is instant. A subcommand whose module cannot
be imported stays listed, marked unavailable with the reason, and using it is
one clear error. Deliberate errors (:class:`cerpe.errors.CerpeError`) are printed
as one line, exit code 2; a closed output pipe (``cerpe eval ... | head``) ends
the command quietly, as Unix tools do.
"""
from __future__ import annotations

import argparse
import importlib
import logging
import os
import signal
import sys
from types import ModuleType

from .errors import CerpeError

# name -> (module, one-line help). Add a line here to add a subcommand.
SUBCOMMANDS: dict[str, tuple[str, str]] = {}
# cerpe's own log level for -qq, -q, (none), -v; other libraries log warnings only, unless -vv.
LOG_LEVELS = {-2: logging.ERROR, -1: logging.WARNING, 0: logging.INFO, 1: logging.DEBUG}
EXIT_BROKEN_PIPE = 128 + signal.SIGPIPE  # what a shell reports for a tool killed by SIGPIPE


def _register(name: str, module: str, help_: str) -> None:
    SUBCOMMANDS[name] = (module, help_)


_register("demo", "cerpe.demo", "a first minute: render one small encounter, run CERPE and a baseline, print a "
          "table and draw one picture (what `make demo` runs)")
_register("synth", "cerpe.synth.cli", "render a synthetic encounter world to a mocap-style dataset")
_register("check", "cerpe.datasets.cli", "validate a dataset manifest, load it and summarise it")
_register("config", "cerpe.config_show", "print the method's configuration tree: every knob, its meaning and unit")
_register("run", "cerpe.pipeline.run", "run a method (cerpe, cerpe-wo-em, baselines) on a manifest")
_register("eval", "cerpe.pipeline.eval_cli", "compute the paper's metrics for a run folder")
_register("export", "cerpe.pipeline.export", "export a run folder's estimates and ground truth as COLMAP text models")
_register("bench", "cerpe.pipeline.bench", "benchmark per-stage latency, memory and bytes")
_register("paper", "cerpe.pipeline.paper", "build every table and figure (what `make paper` runs)")
_register("dev", "cerpe.pipeline.dev", "development report: the five methods on the real development sets and "
          "synthetic development seeds (never the paper-default suite), and the development checks")
_register("fit", "cerpe.fit.cli", "fit the files shipped in cerpe/data/ on development data: descriptor centres "
          "and mean, the codecs' projection, the gate's thresholds")
_register("online", "cerpe.online.cli", "run ONE robot of a team online, talking to its peers over Zenoh")
_register("bag", "cerpe.online.bag_cli", "ROS bags: play one on Zenoh as a robot's topics, write a dataset as bags, "
          "list a bag")
_register("data", "cerpe.datasets.data_cli", "list public datasets, download one (resumable, checked) and print its manifest")


class CommandUnavailable(CerpeError):
    """A subcommand whose module (or one of its imports) cannot be imported here."""


def _import(module: str) -> tuple[ModuleType | None, str]:
    """``(module, "")``, or ``(None, why)`` when importing it fails (a missing package, a broken install)."""
    try:
        return importlib.import_module(module), ""
    except (ImportError, OSError) as exc:  # OSError: a shared library that does not load
        return None, f"importing {module} failed: {type(exc).__name__}: {exc}"


def _verbosity_args(p: argparse.ArgumentParser, top: bool) -> None:
    # On the subcommands too, so that `cerpe run ... -v` works; SUPPRESS keeps the top-level count.
    default = 0 if top else argparse.SUPPRESS
    p.add_argument("-v", "--verbose", action="count", default=default,
                   help="more log output: debug messages of cerpe (-vv: of every library too)")
    p.add_argument("-q", "--quiet", action="count", default=default,
                   help="less log output: warnings and errors only (-qq: errors only)")


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
    _verbosity_args(parser, top=True)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_) in SUBCOMMANDS.items():
        mod, why = _import(module)
        if mod is None:
            p = sub.add_parser(name, help=f"UNAVAILABLE here ({why}); {help_}",
                               description=f"{help_}\n\nUNAVAILABLE here: {why}",
                               formatter_class=argparse.RawDescriptionHelpFormatter)
            p.set_defaults(_main=_unavailable(name, why), _unavailable=True)
            continue
        p = sub.add_parser(name, help=help_, description=(mod.__doc__ or help_).strip(),
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        mod.add_arguments(p)
        _verbosity_args(p, top=False)
        p.set_defaults(_main=mod.main)
    return parser


def _unavailable(name: str, why: str):
    def main(args: argparse.Namespace) -> int:
        raise CommandUnavailable(f"this command is unavailable here: {why} "
                                 f"(reinstall cerpe with its dependencies: make setup)")
    return main


def setup_logging(verbose: int, quiet: int) -> int:
    """Configure logging from the -v / -q counts; returns cerpe's log level."""
    n = verbose - quiet
    level = LOG_LEVELS[max(-2, min(1, n))]
    others = logging.DEBUG if n >= 2 else max(level, logging.WARNING)
    logging.basicConfig(level=others, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("cerpe").setLevel(level)
    return level


def _quiet_stdout() -> None:
    """After a broken pipe: point stdout at /dev/null so the interpreter's final flush stays silent."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):  # stdout replaced by something without a descriptor (tests)
        pass
    finally:
        os.close(devnull)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra and not getattr(args, "_unavailable", False):  # an unavailable command's arguments are moot
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    setup_logging(args.verbose, args.quiet)
    if not getattr(args, "_main", None):
        parser.print_help()
        return 2
    try:
        rc = int(args._main(args) or 0)
        sys.stdout.flush()  # a closed pipe shows here, inside the handler, not at exit
        return rc
    except BrokenPipeError:
        _quiet_stdout()
        return EXIT_BROKEN_PIPE
    except CerpeError as exc:
        print(f"cerpe {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"cerpe {args.command}: interrupted; rerun the same command to resume", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
