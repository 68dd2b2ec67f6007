"""Configs holding values their type does not allow, as a user's plain Python call can make them.

The suite runs with jaxtyping's import hook, which type-checks every dataclass constructor against its annotations
(a `Literal` included) and so refuses `GraspConfig(sampler="learned")` before the package's own check could speak.
A user's process has no hook: the package's check is what they meet, and what these tests must reach."""

import dataclasses


def with_bad(cfg, **fields):
    """`cfg` with `fields` set past the constructor's type check (a frozen dataclass: set as its __init__ would)."""
    out = dataclasses.replace(cfg)
    for name, value in fields.items():
        object.__setattr__(out, name, value)
    return out
