"""The ``seqtrojan`` command: one subcommand per stage, each parsed by tyro from a typed dataclass.

seqtrojan demo --out outputs/demo
seqtrojan <command> --help
"""

from __future__ import annotations

import sys
from collections.abc import Callable

import tyro

from seqtrojan.errors import SeqTrojanError


def _demo(argv: list[str]) -> None:
    from seqtrojan.demo import DemoArgs, run_demo

    run_demo(tyro.cli(DemoArgs, args=argv, prog="seqtrojan demo"))


COMMANDS: dict[str, tuple[Callable[[list[str]], None], str]] = {
    "demo": (_demo, "build envs, run random and scripted agents, render episodes (text and PNG)"),
}


def _usage() -> str:
    lines = ["usage: seqtrojan <command> [options]", "", "commands:"]
    lines += [f"  {name:<10} {help_}" for name, (_, help_) in COMMANDS.items()]
    lines += ["", "Run 'seqtrojan <command> --help' for a command's options."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return 0
    if argv[0] in ("-V", "--version"):
        from seqtrojan import __version__

        print(f"seqtrojan {__version__}")
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"seqtrojan: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    try:
        COMMANDS[name][0](rest)
    except SeqTrojanError as err:
        print(f"seqtrojan {name}: error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
