"""The `flamenerf` command: one subcommand per pipeline step.

Each subcommand is a typed function in `flamenerf.commands.<name>` whose docstring is its
`--help`; heavy libraries are imported inside the functions so `--help` stays fast.
"""

from __future__ import annotations

import importlib
import os
import sys

# Order shown in --help: the pipeline, then tools.
COMMANDS = ["demo", "synth", "preprocess", "track", "train", "eval", "compare", "render",
            "view", "bench"]


def _tune_allocator() -> None:
    # glibc returns large freed blocks to the OS and then page-faults them back on every
    # training step; keeping them mapped made steps ~2x faster on CPU (PERF_NOTES.md).
    # The variables are read at process start, so re-exec once with them set.
    want = {"MALLOC_MMAP_MAX_": "0", "MALLOC_TRIM_THRESHOLD_": "100000000000"}
    if sys.platform.startswith("linux") and any(os.environ.get(k) != v for k, v in want.items()):
        if os.environ.get("FLAMENERF_NO_REEXEC"):
            return
        env = dict(os.environ, **want, FLAMENERF_NO_REEXEC="1")
        os.execve(sys.executable, [sys.executable, "-m", "flamenerf.cli", *sys.argv[1:]], env)


def available_commands() -> dict:
    cmds = {}
    for name in COMMANDS:
        try:
            mod = importlib.import_module(f"flamenerf.commands.{name}")
        except ModuleNotFoundError as e:
            if e.name == f"flamenerf.commands.{name}":
                continue  # not built yet
            raise
        cmds[name] = getattr(mod, name)
    return cmds


def main(argv: list[str] | None = None) -> int:
    import tyro

    from flamenerf.errors import UserError

    if argv is None and any(a in sys.argv[1:2] for a in ("train", "bench", "demo", "eval")):
        _tune_allocator()
    cmds = available_commands()
    try:
        tyro.extras.subcommand_cli_from_dict(
            cmds, prog="flamenerf", args=argv, description=__doc__.splitlines()[0]
        )
    except UserError as e:
        print(f"flamenerf: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("flamenerf: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
