"""`cadence`: the one console script (DESIGN §10). Every subcommand has --help; bad input exits 2 with
one line naming the file and field; nothing is written when the input is bad. One module per family of
commands; each declares a command above the function that runs it (``Commands`` in _common.py)."""

from __future__ import annotations

import argparse
import os
import sys

from cadence import version
from cadence.cli import bench, bench_people, cell, demo, deploy, hrv, lab, operate, plan, session
from cadence.cli._common import SERVICES, err
from common.runtime.errors import BusError, CadenceError, InputError

__all__ = ["SERVICES", "build_parser", "main"]


class _Version(argparse.Action):
    """``--version``, its version read only when asked for (``version()``: importlib.metadata's cost)."""

    def __call__(self, parser: argparse.ArgumentParser, *_: object) -> None:
        sys.stdout.write(f"cadence {version()}\n")
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cadence",
        description="Cadence: a cobot that keeps a pace its human co-worker can sustain.",
    )
    parser.add_argument("--version", action=_Version, nargs=0, help="show the version and exit")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    assert bench_people.cli is bench.cli  # its commands are of the bench family
    for family in (plan, bench, cell, operate, demo, lab, session, hrv, deploy):
        family.cli.add(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # said by the command's own parser, with its usage, not the top level's
        getattr(args, "command_parser", parser).error(f"unrecognized arguments: {' '.join(unknown)}")
    try:
        return int(args.func(args))
    except InputError as exc:
        err.print(f"cadence: error: {exc}", markup=False, highlight=False, soft_wrap=True)
        return 2
    except BusError as exc:
        err.print(f"cadence: bus error: {exc}", markup=False, highlight=False, soft_wrap=True)
        return 1
    except CadenceError as exc:
        err.print(f"cadence: error: {exc}", markup=False, highlight=False, soft_wrap=True)
        return 1
    except KeyboardInterrupt:
        err.print("cadence: interrupted")
        return 130
    except BrokenPipeError:  # `cadence hrv peaks … | head`: the reader has had enough
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    sys.exit(main())
