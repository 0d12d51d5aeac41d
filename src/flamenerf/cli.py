"""The `flamenerf` command: one subcommand per pipeline step.

Each subcommand is a typed function in `flamenerf.commands.<name>` whose docstring is its
`--help`; where the library has an options dataclass (render, preprocess, view, bench) the
function takes it whole and its fields are the flags. Heavy libraries are imported inside
the functions so `--help` stays fast.
"""

from __future__ import annotations

import importlib
import os
import sys

# Order shown in --help: the pipeline, then tools.
COMMANDS = ["demo", "synth", "preprocess", "track", "train", "eval", "compare", "render",
            "view", "bench", "convert"]


def _tune_allocator() -> None:
    from flamenerf.runtime import reexec_with_tuned_allocator

    reexec_with_tuned_allocator(["-m", "flamenerf.cli", *sys.argv[1:]])


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

    from flamenerf.errors import Interrupted, UserError

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
    except Interrupted as e:
        print(f"flamenerf: interrupted: {e}", file=sys.stderr)
        return 130
    except KeyboardInterrupt:
        print("flamenerf: interrupted", file=sys.stderr)
        return 130
    except OSError as e:
        # the machine said no (full disk, read-only or vanished folder): one line naming
        # the file; FLAMENERF_DEBUG=1 shows the traceback
        if os.environ.get("FLAMENERF_DEBUG"):
            raise
        where = f"{e.filename}: " if e.filename else ""
        print(f"flamenerf: error: {where}{e.strerror or e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
