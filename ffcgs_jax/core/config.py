"""What every config shares: TOML loading, dict-to-dataclass with unknown keys refused, range checks.

Each subpackage owns its configs (`geometry.config`, `synthesis.config`, `physics.config`, `dataset.config`,
`learning.config`, `training.config`, `viz.config`); every command's options are one nested frozen dataclass of them. `load(cls,
path)` reads a TOML file into it; the CLI then lets any field be overridden (`--sdf.res 64`). Frozen dataclasses
hash, so a config can be a static jit argument.

A renamed setting keeps its old name readable: the dataclass lists `RENAMED: ClassVar[dict[str, str]]` (old name ->
new), and TOML files, saved configs and CLI flags under the old name still load, with one line naming the new key.
A choice among names is a `typing.Literal`; `from_dict`, `check_choice` and the CLI's parser all read its values.
"""

import contextlib
import dataclasses
import functools
import io
import math
import sys
import tomllib
import typing
import warnings
from pathlib import Path
from typing import Any, TypeVar

from ffcgs_jax.core.errors import FfcgsError

T = TypeVar("T")
SEED_MAX = 2**63 - 1  # seeds are int64 (JAX's and NumPy's PRNG keys take them)


def check_range(name: str, value: int | float, lo: int | float, hi: int | float) -> None:
    """Refuse `value` outside [lo, hi], or not a number (NaN, a string, a bool), naming the config key `name`."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not lo <= value <= hi:
        raise FfcgsError(f"{name} must be in [{lo}, {hi}], got {value!r}")


def check_integer(name: str, value: Any, lo: int, hi: int) -> None:
    """Like `check_range`, for a field that must be a true int (not a bool, not a float from a TOML typo)."""
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise FfcgsError(f"{name} must be an integer in [{lo}, {hi}], got {value!r}")


def check_choice(name: str, value: Any, choices: Any) -> None:
    """Refuse `value` outside `choices` (a `typing.Literal` or a tuple of names), listing the valid ones."""
    valid = typing.get_args(choices) or tuple(choices)
    if not isinstance(value, str) or value not in valid:
        raise FfcgsError(f"unknown {name} {value!r}; choices: {', '.join(map(str, valid))}")


def renamed(cls: type) -> dict[str, str]:
    """A config class's old field names -> their new names (`RENAMED`), {} for one never renamed."""
    return dict(getattr(cls, "RENAMED", {}))


def _say_renamed(old: str, new: str) -> None:
    warnings.warn(f"{old} is now called {new}; the old name still reads, but write {new}", FutureWarning,
                  stacklevel=3)


def keeps_old_names(cls: type[T]) -> type[T]:
    """Class decorator for a config dataclass with `RENAMED` fields: a Python keyword under the old name
    (`PhysicsConfig(friction=0.5)`, `dataclasses.replace(cfg, friction=0.5)`) sets the new field, with one line
    naming it, as a TOML key or a flag does."""
    init = cls.__init__

    @functools.wraps(init)
    def __init__(self, *args, **kwargs):
        for old, new in renamed(cls).items():
            if old in kwargs:
                if new in kwargs:  # also `dataclasses.replace(cfg, old=...)`, which passes every field by name
                    raise FfcgsError(f"{cls.__name__}: {old} is now called {new}; give {new} alone")
                kwargs[new] = kwargs.pop(old)
                _say_renamed(f"{cls.__name__}({old}=...)", f"{cls.__name__}({new}=...)")
        init(self, *args, **kwargs)

    cls.__init__ = __init__
    return cls


def upgrade_keys(cls: type, data: Any, where: str = "", say: bool = False) -> Any:
    """`data` (a config's nested dict, as a file stored it) with every old key of `cls` and its sections under its
    new name; anything not a config key is left as it is. `say`: one line per renamed key."""
    if not isinstance(data, dict) or not dataclasses.is_dataclass(cls):
        return data
    out = dict(data)
    for old, new in renamed(cls).items():
        if old in out:
            if new in out:
                raise FfcgsError(f"config keys {where}{old} and {where}{new} are both set: {old} is the old name of "
                                 f"{new}; keep {new} alone")
            out[new] = out.pop(old)
            if say:
                _say_renamed(where + old, where + new)
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if f.name in out and dataclasses.is_dataclass(hints[f.name]):
            out[f.name] = upgrade_keys(hints[f.name], out[f.name], f"{where}{f.name}.", say)
    return out


def is_finite(value: Any) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value)


def from_dict(cls: type[T], data: Any, where: str = "", base: Any = None, say_renamed: bool = True) -> T:
    """Build dataclass `cls` from a nested dict, naming any unknown key and listing the valid ones.

    A key under its old name (`RENAMED`) reads as its new one, with one line saying so unless `say_renamed` is
    False (a file the program saved, not one the user writes).

    Keys a table leaves out keep their defaults, and a nested table changes only the keys it names: its other keys
    keep the enclosing config's default for that section (`base`), not the section class's own defaults (a
    dataset's `[grasp]` table with only `n` keeps the dataset's geometric sampler)."""
    if not isinstance(data, dict):
        raise FfcgsError(f"config section {where.rstrip('.') or '<top>'} must be a table, got {type(data).__name__}")
    data = upgrade_keys(cls, data, where, say_renamed)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    # keys as printable text: a TOML quoted key may hold a newline (the message must stay one line), and a dict
    # built in Python may have non-string keys (which `where + k` and sorting would trip on)
    unknown = sorted(k if isinstance(k, str) and k.isprintable() else repr(k) for k in set(data) - set(fields))
    if unknown:
        raise FfcgsError(
            f"unknown config key(s) {', '.join(where + k for k in unknown)}; "
            f"valid keys{' in ' + where.rstrip('.') if where else ''}: {', '.join(sorted(fields))}"
        )
    kwargs = {}
    for name, value in data.items():
        hint = hints[name]
        if dataclasses.is_dataclass(hint):
            inner = getattr(base, name) if base is not None else _default(fields[name])
            kwargs[name] = from_dict(hint, value, f"{where}{name}.", inner, say_renamed)
        else:
            kwargs[name] = coerce(hint, value, where + name)
    obj = cls(**kwargs) if base is None else dataclasses.replace(base, **kwargs)
    check_all(obj)
    return obj


def _default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    return f.default_factory() if f.default_factory is not dataclasses.MISSING else None


def coerce(hint: Any, value: Any, name: str) -> Any:
    args = typing.get_args(hint)
    if typing.get_origin(hint) is typing.Literal:
        check_choice(f"config key {name}", value, hint)
        return value
    if type(None) in args and len(args) == 2:  # `X | None`: None stays, anything else must be an X
        return None if value is None else coerce(next(a for a in args if a is not type(None)), value, name)
    if hint is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if hint in (int, float, str, bool) and (
            not isinstance(value, hint) or (isinstance(value, bool) and hint is not bool)):
        raise FfcgsError(f"config key {name} must be {hint.__name__}, got {value!r}")
    if typing.get_origin(hint) is tuple:
        if not isinstance(value, (list, tuple)):
            raise FfcgsError(f"config key {name} must be a list, got {value!r}")
        if not args:
            return tuple(value)
        items = args[:1] * len(value) if args[1:] == (...,) else args
        if len(items) != len(value):
            raise FfcgsError(f"config key {name} must be a list of {len(items)} values, got {value!r}")
        return tuple(coerce(t, v, f"{name}[{i}]") for i, (t, v) in enumerate(zip(items, value)))
    return value


def check_all(obj: Any) -> None:
    """Run `check()` on a config and on every nested config, so CLI overrides are validated too."""
    for f in dataclasses.fields(obj):
        sub = getattr(obj, f.name)
        if dataclasses.is_dataclass(sub):
            check_all(sub)
    if hasattr(obj, "check"):
        obj.check()


def load(cls: type[T], path: str | Path) -> T:
    """Read a TOML file into config class `cls` (missing keys keep their defaults)."""
    return from_dict(cls, read_toml(path))


def read_toml(path: str | Path, what: str = "config file") -> dict:
    """The tables of a TOML file (`what`: how messages name it), or FfcgsError naming a missing or malformed file."""
    from ffcgs_jax.core.files import read_text

    text = read_text(path, what)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise FfcgsError(f"{what} {path} is not valid TOML: {e}") from None
    except RecursionError:  # tomllib recurses per nesting level: `a = [[[...]]]` a thousand deep
        raise FfcgsError(f"{what} {path} is not usable: its arrays or tables nest too deep") from None


def split_config_arg(argv: list[str]) -> tuple[str | None, list[str]]:
    """(the `--config FILE` path or None, the other arguments)."""
    rest, path = [], None
    it = iter(argv)
    for a in it:
        if a == "--config":
            path = next(it, None)
            if path is None:
                raise FfcgsError("--config needs a file path")
        elif a.startswith("--config="):
            path = a.split("=", 1)[1]
        else:
            rest.append(a)
    return path, rest


def with_overrides(cls: type[T], argv: list[str], prog: str, keep_prefixes: bool = False,
                   description: str | None = None) -> T:
    """Config `cls` from `--config FILE.toml` (if in `argv`) and then the command-line overrides in `argv`.

    Nested sections' fields are flags without their section prefix (`--res 64`) unless `keep_prefixes`, for
    configs whose sections share field names (`--planner.population 4096`). Every value is range-checked.
    """
    import tyro  # only the CLI needs it

    path, argv = split_config_arg(argv)
    argv = respell_flags(cls, argv, keep_prefixes)
    default = cls() if path is None else load(cls, path)
    captured = io.StringIO()
    try:
        with contextlib.redirect_stderr(captured):
            cfg = tyro.cli(cls, default=default, args=argv, prog=prog,
                           config=() if keep_prefixes else (tyro.conf.OmitArgPrefixes,),
                           description=description or cls.__doc__)
    except SystemExit as e:
        if e.code in (0, None):  # --help
            sys.stderr.write(captured.getvalue())
            raise
        raise FfcgsError(f"{prog}: {_one_line(captured.getvalue())} (see {prog} --help)") from None
    sys.stderr.write(captured.getvalue())  # tyro's warnings, if any
    check_all(cfg)
    return cfg


def leaf_paths(cls: type) -> list[str]:
    """Dotted paths of a config's settings (`optim.iters`), nested sections walked."""
    hints = typing.get_type_hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        if dataclasses.is_dataclass(hints[f.name]):
            out += [f"{f.name}.{p}" for p in leaf_paths(hints[f.name])]
        else:
            out.append(f.name)
    return out


def renamed_paths(cls: type) -> dict[str, str]:
    """Old dotted paths of renamed settings -> their new paths (`physics.friction` -> `physics.sim_friction`)."""
    hints = typing.get_type_hints(cls)
    out = {old: new for old, new in renamed(cls).items()}
    for f in dataclasses.fields(cls):
        if dataclasses.is_dataclass(hints[f.name]):
            out |= {f"{f.name}.{o}": f"{f.name}.{n}" for o, n in renamed_paths(hints[f.name]).items()}
    return out


def respell_flags(cls: type, argv: list[str], keep_prefixes: bool) -> list[str]:
    """Both spellings of a nested setting on every command: `--optim.iters 50` where flags are bare (`ffcgs grasp`),
    and `--population 64` where they keep their section (`ffcgs dataset build`) when only one section has that
    name. Each is rewritten to the command's own spelling, so help and errors stay the parser's."""
    paths = {p.replace("_", "-"): p for p in leaf_paths(cls)}
    by_leaf: dict[str, list[str]] = {}
    for p in paths:
        by_leaf.setdefault(p.rsplit(".", 1)[-1], []).append(p)
    old_paths = {o.replace("_", "-"): n.replace("_", "-") for o, n in renamed_paths(cls).items()}
    old_by_leaf: dict[str, list[str]] = {}
    for o in old_paths:
        old_by_leaf.setdefault(o.rsplit(".", 1)[-1], []).append(o)
    out = []
    for a in argv:
        flag, eq, value = a.partition("=")
        if not flag.startswith("--") or flag == "--":
            out.append(a)
            continue
        name = flag[2:].replace("_", "-")
        old = name if name in old_paths else None
        if old is None and name not in by_leaf and len(old_by_leaf.get(name, ())) == 1:
            old = old_by_leaf[name][0]
        if old is not None:  # a renamed setting's old flag: read as the new one, in the spelling it came in
            name = old_paths[old] if "." in name else old_paths[old].rsplit(".", 1)[-1]
            _say_renamed(flag, "--" + name)
            flag = "--" + name
        if not keep_prefixes and "." in name and name in paths and len(by_leaf[name.rsplit(".", 1)[-1]]) == 1:
            flag = "--" + name.rsplit(".", 1)[-1]
        elif keep_prefixes and "." not in name and len(by_leaf.get(name, ())) == 1 and "." in by_leaf[name][0]:
            flag = "--" + by_leaf[name][0]
        out.append(flag + eq + value)
    return out


_BOX = "│╭╮╰╯─┃┏┓┗┛━"


def _one_line(text: str) -> str:
    """tyro's boxed parse error as one line: the box's title and its first paragraph."""
    lines = [ln.strip().strip(_BOX).strip() for ln in text.splitlines()]
    title = lines[0].strip(_BOX + " ") if lines else ""
    body = []
    for ln in lines[1:]:
        if not ln.strip(_BOX + " -"):
            if body:
                break
            continue
        if set(ln) <= set(_BOX + " -"):  # the separator before the help text (dashes without a terminal font)
            break
        body.append(ln)
    message = " ".join(body) or "invalid arguments"
    return f"{title.lower()}: {message}" if title else message
