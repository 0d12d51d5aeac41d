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
            "view", "bake", "export", "bench", "convert"]


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
        command = getattr(mod, name)
        # tyro reads the parameters' help from the function itself, behind the wrapper
        # (an options dataclass's fields it reads its own way: left as they are)
        command.__doc__ = reflowed(command.__doc__ or "")
        cmds[name] = _finite_floats(command)
    return cmds


def reflowed(doc: str) -> str:
    """A command's docstring with each paragraph, and each `Args:` entry, on one line:
    tyro keeps a function parameter's line breaks, and breaks a description before any
    line that starts with a non-letter (`(driven)`), so `eval --help` broke mid-sentence.
    Paragraphs that are lists (a line starting with `- `) keep their lines."""
    import inspect

    out: list[str] = []
    in_args = False
    for para in inspect.cleandoc(doc).split("\n\n"):
        lines = para.split("\n")
        if lines[0].strip() == "Args:" or in_args and lines[0].startswith(" "):
            in_args = True
            entries: list[str] = [lines[0]] if lines[0].strip() == "Args:" else []
            for line in lines[len(entries):]:
                indent = len(line) - len(line.lstrip())
                if entries and indent > 4 and not entries[-1].strip() == "Args:":
                    entries[-1] += " " + line.strip()  # an entry's continuation
                else:
                    entries.append(line)
            out.append("\n".join(entries))
        elif any(line.lstrip().startswith("- ") for line in lines):
            in_args = False
            out.append(para)
        else:
            in_args = False
            out.append(" ".join(line.strip() for line in lines))
    return "\n\n".join(out)


def _non_finite(value, flag: str) -> str | None:
    """The flag of the first float in `value` (an argument, an options dataclass's fields,
    a list's items) that is NaN or infinite, else None."""
    import dataclasses
    import math

    if isinstance(value, float):
        return flag if not math.isfinite(value) else None
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        for f in dataclasses.fields(value):
            bad = _non_finite(getattr(value, f.name), "--" + f.name.replace("_", "-"))
            if bad:
                return bad
    if isinstance(value, (list, tuple)):
        return next(filter(None, (_non_finite(v, flag) for v in value)), None)
    return None


def _finite_floats(command):
    """`command`, refusing NaN and infinite numbers in any of its float options with one
    line (tyro parses "nan" and "inf" as floats; no option here means either)."""
    import functools
    import inspect

    sig = inspect.signature(command)

    @functools.wraps(command)
    def checked(*args, **kwargs):
        from flamenerf.errors import UserError

        bound = sig.bind(*args, **kwargs)
        for name, value in bound.arguments.items():
            # an options dataclass's fields are flags of their own (OmitArgPrefixes)
            bad = _non_finite(value, "--" + name.replace("_", "-"))
            if bad:
                raise UserError(f"{bad}: must be a finite number")
        return command(*args, **kwargs)

    return checked


def list_flags(command) -> set[str]:
    """The flags of `command` (its parameters, and an options dataclass's fields) that take
    several values after one flag (`--edit A B`), tyro's list options without
    UseAppendAction."""
    import dataclasses
    import inspect
    import types
    import typing

    import tyro

    def is_list(hint) -> bool:
        if typing.get_origin(hint) is typing.Annotated:
            hint, *extra = typing.get_args(hint)
            if any(e is tyro.conf.UseAppendAction for e in extra):
                return False
        if typing.get_origin(hint) in (typing.Union, types.UnionType):
            return any(is_list(a) for a in typing.get_args(hint) if a is not type(None))
        return typing.get_origin(hint) in (list, tuple)

    out = set()
    hints = typing.get_type_hints(inspect.unwrap(command), include_extras=True)
    for name, hint in hints.items():
        base = typing.get_args(hint)[0] if typing.get_origin(hint) is typing.Annotated else hint
        if dataclasses.is_dataclass(base):
            fields = typing.get_type_hints(base, include_extras=True)
            out |= {"--" + f.replace("_", "-") for f, h in fields.items() if is_list(h)}
        elif name != "return" and is_list(hint):
            out.add("--" + name.replace("_", "-"))
    return out


def flag_name(token: str) -> str:
    """An option as tyro takes it: `--side_by_side` is `--side-by-side`."""
    return "--" + token[2:].replace("_", "-") if token.startswith("--") else token


def merge_repeated(args: list[str], flags: set[str]) -> list[str]:
    """`--edit A --edit B` as `--edit A B`: tyro (argparse) keeps only a list flag's last
    occurrence, which silently dropped the first edit. Each flag of `flags` given more than
    once is given once, at its first place, with all its values in order."""
    def is_flag(a: str) -> bool:
        return a.startswith("--") or (len(a) == 2 and a[0] == "-" and a[1].isalpha())

    values: dict[str, list[str]] = {}
    order: list[tuple[str, object]] = []  # ("arg", token) or ("flag", name)
    i = 0
    while i < len(args):
        a = args[i]
        if a == "--":  # what follows is not options
            order += [("arg", t) for t in args[i:]]
            break
        name, eq, inline = a.partition("=")
        name = flag_name(name)
        if name in flags:
            j = i + 1
            while j < len(args) and not is_flag(args[j]):
                j += 1
            if name not in values:
                values[name] = []
                order.append(("flag", name))
            values[name] += ([inline] if eq else []) + args[i + 1:j]
            i = j
            continue
        order.append(("arg", a))
        i += 1
    out: list[str] = []
    for kind, tok in order:
        out += [tok, *values[tok]] if kind == "flag" else [tok]
    return out


def unknown_option(name: str, args: list[str], command) -> str | None:
    """The one-line error for the first `--option` of `args` that command `name` does not
    take, with this command's nearest option (tyro's own lists options of every command
    in a box); None when all are known, or where this tyro cannot say (its parser then
    reports the error its way)."""
    import warnings

    import tyro

    from flamenerf.keyvalues import suggest

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # get_parser is deprecated in tyro 1.x
            known = sorted(tyro.extras.get_parser(command)._option_string_actions)
    except Exception:  # noqa: BLE001 - only a nicer message is lost
        return None
    for a in args:
        if a == "--":
            break
        flag = a.split("=", 1)[0]
        if flag.startswith("--") and flag not in known and flag_name(flag) not in known:
            return (f"{flag}: not an option of `flamenerf {name}`{suggest(flag, known)} "
                    f"(`flamenerf {name} --help` lists them)")
    return None


def summary(command) -> str:
    """A command's docstring's first sentence, on one line."""
    import re

    first = " ".join((command.__doc__ or "").strip().split("\n\n")[0].split())
    return re.split(r"(?<=\.)\s", first)[0]


def short_help(cmds: dict) -> str:
    """`flamenerf --help`: one line or two per subcommand. tyro's own lists every
    subcommand's whole docstring (~220 lines); each `flamenerf NAME --help` keeps it."""
    import textwrap

    width = max(len(n) for n in cmds) + 4
    lines = [f"usage: flamenerf [-h] {{{','.join(cmds)}}} ...", "",
             __doc__.splitlines()[0], "", "commands:"]
    for name, command in cmds.items():
        lines += textwrap.wrap(summary(command), 88, initial_indent=f"  {name:<{width - 2}}",
                               subsequent_indent=" " * width)
    lines += ["", "`flamenerf NAME --help` shows a command's options and an example; "
              "`flamenerf --version` the version."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    import tyro

    from flamenerf.errors import Interrupted, UserError

    args = sys.argv[1:] if argv is None else argv
    if args in (["-h"], ["--help"]):
        print(short_help(available_commands()))
        return 0
    if args in (["-V"], ["--version"]):
        from flamenerf import __version__

        print(f"flamenerf {__version__}")
        return 0
    if argv is None and any(a in sys.argv[1:2] for a in ("train", "bench", "demo", "eval")):
        _tune_allocator()
    cmds = available_commands()
    if args and not args[0].startswith("-") and args[0] not in cmds:
        from flamenerf.keyvalues import suggest

        print(f"flamenerf: error: {args[0]!r} is not a command{suggest(args[0], list(cmds))} "
              "(`flamenerf --help` lists them)", file=sys.stderr)
        return 2
    if os.environ.get("FLAMENERF_GPU_KERNELS", "").strip() not in ("", "0", "1"):
        from flamenerf.gpu_kernels import chosen

        try:  # a mistyped kernel name: said now, not at the first render after training
            chosen()
        except UserError as e:
            print(f"flamenerf: error: {e}", file=sys.stderr)
            return 2
    if args and args[0] in cmds:
        merged = merge_repeated(args[1:], list_flags(cmds[args[0]]))
        if merged != args[1:]:
            argv = [args[0], *merged]
        bad = unknown_option(args[0], merged, cmds[args[0]])
        if bad:
            print(f"flamenerf: error: {bad}", file=sys.stderr)
            return 2
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
    except (MemoryError, RuntimeError) as e:
        # an option asked for more than the machine has (a huge --batch-rays, --size,
        # --frames): one line, not the allocator's traceback
        oom = (isinstance(e, MemoryError) or type(e).__name__ == "OutOfMemoryError"
               or "DefaultCPUAllocator" in str(e) or "out of memory" in str(e))  # (MPS)
        from flamenerf import gpu_kernels

        if gpu_kernels.gpu_faulted(e) and not os.environ.get("FLAMENERF_DEBUG"):
            # the GPU's context is lost; the likeliest cause is one of our Triton kernels
            what = (gpu_kernels.first_line(e) if isinstance(e, gpu_kernels.GPUFault)
                    else f"the GPU faulted ({gpu_kernels.first_line(e)})")
            print(f"flamenerf: error: {what}; {gpu_kernels.fault_advice()}", file=sys.stderr)
            return 1
        if not oom or os.environ.get("FLAMENERF_DEBUG"):
            raise
        print("flamenerf: error: out of memory: the options ask for more than this machine "
              "has (lower sizes, frames or rays per step)", file=sys.stderr)
        return 1
    except OSError as e:
        # the machine said no (full disk, read-only or vanished folder): one line naming
        # the file; FLAMENERF_DEBUG=1 shows the traceback
        if os.environ.get("FLAMENERF_DEBUG"):
            raise
        import errno

        if e.errno == errno.EPIPE:  # `flamenerf X --help | head`: the reader has gone
            return 0
        where = f"{e.filename}: " if e.filename else ""
        print(f"flamenerf: error: {where}{e.strerror or e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
