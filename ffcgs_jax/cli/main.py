"""The `ffcgs` command: one subcommand per job (`cli.commands`), options from frozen config dataclasses.

Every subcommand takes `--config FILE.toml` (sections as in `configs/`) and then command-line overrides
(`ffcgs sdf mug --res 64`). Bad input ends with one line on stderr and exit status 2, never a traceback.
"""

import os
import re
import signal
import sys
import textwrap
import threading
import warnings

# Only the standard library above this line: `main` sets its Ctrl-C handler before anything slow is imported, so an
# interrupt in the first second is the same one line as later (`_package` brings in the rest).

# Composite configs whose nested sections share field names (seed, filters) keep their prefixes on the command
# line: `ffcgs dataset build --per-object 200 --planner.population 4096 --physics.sim-friction 0.6`.
_PREFIXED = {"dataset build", "learn"}


def _usage() -> str:
    from ffcgs_jax.cli import train_command
    from ffcgs_jax.cli.commands import COMMANDS

    lines = ["usage: ffcgs COMMAND [--config FILE.toml] [options]", "", "commands:"]
    docs = {name: cls.__doc__ for name, (cls, _) in COMMANDS.items()} | {"train": train_command.__doc__}
    for name, doc in docs.items():
        lines += textwrap.wrap(description(doc), 100, initial_indent=f"  {name:<15}", subsequent_indent=" " * 17,
                               break_on_hyphens=False)
    lines += ["", "`ffcgs COMMAND --help` lists a command's options."]
    return "\n".join(lines)


def first_sentence(doc: str | None) -> str:
    """A docstring's first sentence, over however many lines it runs, without a leading "`ffcgs NAME`: "."""
    text = " ".join((doc or "").strip().split("\n\n")[0].split())
    text = re.sub(r"^`ffcgs [\w -]+`: (\w)", lambda m: m.group(1).upper(), text)
    end = re.search(r"[.!?](?=\s+[A-Z])", text)
    return text[:end.end()] if end else text


def description(doc: str | None) -> str:
    """A command's line in `ffcgs --help`: its docstring's first sentence, whole; one of over 120 characters ends
    at its first colon outside brackets and quotes, where a complete phrase ends, so the list stays a list."""
    text = first_sentence(doc)
    if len(text) <= 120:
        return text
    depth, quoted = 0, False
    for i, c in enumerate(text):
        depth += c in "([{"
        depth -= c in ")]}"
        quoted ^= c in "`\""
        if c == ":" and depth == 0 and not quoted:
            return text[:i] + "."
    return text


def parse(argv: list[str]):
    """Parse `ffcgs COMMAND ...` into (run function, command dataclass); `parse_command` also gives its name."""
    _, fn, cmd = parse_command(argv)
    return fn, cmd


def parse_command(argv: list[str]):
    """Parse `ffcgs COMMAND ...` into (command name, run function, command dataclass)."""
    from ffcgs_jax.cli.commands import COMMANDS
    from ffcgs_jax.core.config import with_overrides
    from ffcgs_jax.core.errors import FfcgsError

    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        raise SystemExit(0 if argv else 2)
    name, argv = argv[0], argv[1:]
    if name == "dataset":
        subs = [c.split(" ", 1)[1] for c in COMMANDS if c.startswith("dataset ")]
        if not argv or argv[0] not in subs:
            raise FfcgsError(f"ffcgs dataset needs a subcommand: {', '.join(subs)}")
        name, argv = f"dataset {argv[0]}", argv[1:]
    if name not in COMMANDS:
        raise FfcgsError(f"unknown command {name!r}; commands: {', '.join(COMMANDS)}")
    cls, fn = COMMANDS[name]
    if name == "grasp":
        argv = _object_flag_as_positional(argv)
    cmd = with_overrides(cls, argv, f"ffcgs {name}", keep_prefixes=name in _PREFIXED)
    return name, fn, cmd


def _object_flag_as_positional(argv: list[str]) -> list[str]:
    """`ffcgs grasp --depth frames/ --object mug`: the object is grasp's positional argument; the flag reads better
    beside --depth, so it is accepted for it."""
    out, i = [], 0
    while i < len(argv):
        a = argv[i]
        if a == "--object" and i + 1 < len(argv):
            out.insert(0, argv[i + 1])
            i += 2
            continue
        if a.startswith("--object="):
            out.insert(0, a.split("=", 1)[1])
        else:
            out.append(a)
        i += 1
    return out


def grasp_line(cmd) -> str:
    """The line `ffcgs grasp` starts with: what it will do, from the parsed options alone."""
    what = ", ".join(cmd.object) if cmd.object else None
    if cmd.depth is not None:
        what = f"depth frames {cmd.depth}" + (f" (true object {what})" if what else "")
    poses = f"the wrist poses of {cmd.poses}" if cmd.poses else f"{cmd.grasp.n} grasps"
    each = " each" if cmd.many else ""
    checked = f", physics-checked ({cmd.protocol})" if cmd.validate else ""
    return f"ffcgs grasp: {what}, hand {cmd.hand}, {poses}{each}{checked}"


_FIRST_LINES = {"grasp": grasp_line}


def _is_terminal(stream) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):  # a replaced or closed stderr
        return False


def _one_line_warning(message, category, filename, lineno, file=None, line=None):
    print(f"ffcgs: warning: {message}", file=sys.stderr if file is None else file)


def _interrupted(signum, frame) -> None:
    # Exit at once: a KeyboardInterrupt raised wherever Python happens to be can land in a garbage-collection
    # callback (and be swallowed), or wait for a compilation to finish. Every file is written through
    # `files.atomic_path`, so removing the temporary files of writes in progress leaves no partial output.
    files = sys.modules.get("ffcgs_jax.core.files")
    if files is not None:  # not loaded yet: no file written yet
        files.discard_temporaries()
    os.write(2, b"\nffcgs: interrupted\n")  # a new line: a progress bar may be half-way through its own
    os._exit(128 + signum)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["train"]:  # own parser (--sweep) and messages: `cli.train_command`, as `python -m train.sampler`
        from ffcgs_jax.cli import train_command

        return train_command.main(argv[1:])
    # SIGTERM too (`timeout`, a job scheduler): Python's default would end the process without cleaning up
    caught = (signal.SIGINT, signal.SIGTERM) if threading.current_thread() is threading.main_thread() else ()
    previous = {sig: signal.signal(sig, _interrupted) for sig in caught}
    try:
        warnings.showwarning = _one_line_warning  # a user needs the message, not our source line
        return _run(argv)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _run(argv: list[str]) -> int:
    from ffcgs_jax.cli import smoke
    from ffcgs_jax.cli.commands import PLANS
    from ffcgs_jax.core.errors import FfcgsError

    try:
        name, fn, cmd = parse_command(argv)
        cmd = smoke.scaled(name, cmd)  # FFCGS_SMOKE: README's commands as written, in seconds (CI)
        plan = PLANS[name](cmd)
        # before anything is loaded or compiled: no output over an input or another output, no folder of another
        # command replaced
        plan.check(f"ffcgs {name}")
        # What the command does, at once on a terminal (before JAX and the meshes load: a cold start is minutes of
        # compile). Into a log or a pipe it comes with the first compile's line instead, so that bad input found
        # while loading stays one line there.
        first = _FIRST_LINES[name](cmd) if name in _FIRST_LINES else None
        if first and _is_terminal(sys.stderr):
            print(first, file=sys.stderr, flush=True)
            first = None
        from ffcgs_jax.runtime import jax_cache, progress  # imports JAX: not before parsing, so --help stays quick

        jax_cache.enable()  # a second run loads its executables from disk (FFCGS_JAX_CACHE=off: compile every time)
        # the large compiles say what compiles, for how long so far, and an estimate (`runtime.progress`)
        with plan.outputs_together(), progress.shown(headline=first):  # all of the command's outputs, or none
            status = fn(cmd)
    except FfcgsError as e:
        print(f"ffcgs: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("ffcgs: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `ffcgs grasp --help | head`: the reader left; say nothing more to it
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141
    return status or 0  # a command that went on past failures says so (`ffcgs grasp` of many objects: 1)


if __name__ == "__main__":
    raise SystemExit(main())
