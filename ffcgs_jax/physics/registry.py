"""The physics protocols as registered objects (as brax registers its environments): `Protocol`, `register`, `get`.

A protocol is one object: its name, the scene it needs (model kind, gravity, table, the closing weld), its steps
(`phases`: the open-loop segments, to watch), how a backend executes it (`execute`), its success rule (`rule`) and
the settings it fixes (`fixed`: DexGraspBench fixes its own friction, mass, gains, solver and bounds), applied in
one place, `Protocol.settings`. The built-in protocols register when `physics.protocols` is imported (it defines
their execution); reach the registry through that module (`protocols.get`), which guarantees they are there.
`physics.config.ALL_PROTOCOLS` names the built-ins without importing the simulation (`protocols` checks them equal).
"""

import dataclasses
import warnings
from collections.abc import Callable, Mapping
from typing import Any

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.physics.config import PhysicsConfig

KINDS = ("ours", "dexgraspbench")  # the scenes a protocol runs on (`world_model.KINDS`)


@dataclasses.dataclass(frozen=True)
class Protocol:
    """One physics protocol.

    Attributes:
        name: what `--protocol` and `protocols=` take, e.g. "six-dir".
        summary: one line saying what it tests.
        kind: the scene's model kind (`KINDS`): "ours" (`scene.build` with `gravity`, `table`, `hold`) or
            "dexgraspbench" (the benchmark's contacts and solver).
        gravity, table, hold: the scene: gravity on, a table under the object, the object welded in place while
            the hand closes.
        execute: `execute(sim, batch, cfg, trial)` drives a backend (`backend.Simulator`) through the protocol and
            records each grasp's measurements in `trial` (`protocols.Trial`), `cfg` already `settings(cfg)`.
        rule: the success rule, `rule(bad_start, lost, move, rot, table, unstable, cfg) -> (success, reason)`
            over per-grasp arrays; the CPU and the GPU worlds (`world_programs`) both judge with it.
        phases: `phases(batch, cfg, mass) -> [(label, Segment, from the branch state)]`: the protocol's steps in
            order, as `viz.physics_video` replays them.
        fixed: the `PhysicsConfig` fields the protocol sets to its own values, whatever the user asked.
        default: one of `config.PROTOCOLS`, what runs when no protocol is named.
        directions: the test pushes along the six `protocols.DIRECTIONS` (results move_dir and rot_dir (B, 6)).
    """

    name: str
    summary: str
    kind: str
    gravity: bool
    table: bool
    hold: bool
    execute: Callable[..., None]
    rule: Callable[..., tuple[Any, Any]]
    phases: Callable[..., list]
    fixed: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    default: bool = False
    directions: bool = False

    def settings(self, cfg: PhysicsConfig) -> PhysicsConfig:
        """`cfg` with the fields this protocol fixes set to its values: the one place they are applied."""
        return dataclasses.replace(cfg, **self.fixed) if self.fixed else cfg

    def overrides(self, cfg: PhysicsConfig) -> list[tuple[str, Any, Any]]:
        """(field, the user's value, the value used) for each fixed field `cfg` set otherwise than its default:
        a default the user never touched is no choice of theirs to override."""
        default = PhysicsConfig()
        return [(k, getattr(cfg, k), v) for k, v in self.fixed.items()
                if getattr(cfg, k) != v and getattr(cfg, k) != getattr(default, k)]


_REGISTRY: dict[str, Protocol] = {}


def register(protocol: Protocol) -> Protocol:
    """Add `protocol` under its name; a name registered before is refused, as is a fixed setting that is no field of
    `PhysicsConfig` (a renamed field would otherwise be silently not fixed)."""
    if protocol.name in _REGISTRY:
        raise FfcgsError(f"physics protocol {protocol.name!r} is registered already")
    if protocol.kind not in KINDS:
        raise FfcgsError(f"protocol {protocol.name!r}: unknown scene kind {protocol.kind!r}; kinds: {', '.join(KINDS)}")
    fields = {f.name for f in dataclasses.fields(PhysicsConfig)}
    unknown = sorted(set(protocol.fixed) - fields)
    if unknown:
        raise FfcgsError(f"protocol {protocol.name!r} fixes {', '.join(unknown)}, which PhysicsConfig does not have")
    _REGISTRY[protocol.name] = protocol
    return protocol


def get(name: str) -> Protocol:
    """The protocol registered as `name`; an unknown name is refused in one line that lists the registered ones."""
    try:
        return _REGISTRY[name]
    except (KeyError, TypeError):
        raise FfcgsError(f"unknown protocol {name!r}; protocols: {', '.join(_REGISTRY)}") from None


def names(default: bool = False) -> tuple[str, ...]:
    """Every registered protocol's name in registration order; `default`: only the default ones."""
    return tuple(n for n, p in _REGISTRY.items() if p.default or not default)


def say_overrides(cfg: PhysicsConfig, protocols) -> None:
    """One warning line naming, per protocol of `protocols`, each setting it fixes that `cfg` set otherwise (the
    user's value and the one used); nothing when there is none. Called once per physics call (`runner.evaluate_many`,
    `viz.physics_video.record`)."""
    said = []
    for p in dict.fromkeys(protocols):
        changed = get(p).overrides(cfg)
        if changed:
            fixed = ", ".join(f"{k} = {used} (you set {user})" for k, user, used in changed)
            said.append(f"protocol {p} fixes {fixed}")
    if said:
        # issued from this line whatever the caller: Python's default filter then says it once, not again for each
        # chunk `validate` simulates or for the video `ffcgs eval` records after its run
        warnings.warn(f"physics: {'; '.join(said)}: the protocol's values are used", stacklevel=1)
