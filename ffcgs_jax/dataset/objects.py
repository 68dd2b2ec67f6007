"""What a dataset build is made of: the objects of a mesh folder's split, generated shapes, their random scales,
and the rule that keeps held-out objects out of training data.

Objects, in build order:
    1. the mesh files of `DatasetConfig.objects` in sorted order; the file at sorted index i is test split when
       i % 5 == 4, else train (the project's split rule for shared/objects/ycb, fixed by position, not by name);
    2. `procedural` generated shapes (`procedural.shape`: boxes, cylinders, ellipsoids, capsules), train split;
    3. `complex` generated shapes (`procedural.complex_shape`: lobes, fins, tori, cups, bowls, C-shapes, plates),
       train split.
Generated shapes come from (`seed`, index) alone, so a build of 3,000 shapes is reproducible anywhere and adding
shapes never changes the earlier ones. Each object is scaled about its origin (they rest on z = 0, centred in x
and y) by a factor drawn uniformly from [scale_min, scale_max] with (seed, name): 1 by default.

Held out: the YCB test split, and the generated sets the benchmarks report on (`procedural.HELD_OUT_SEEDS`). A build
refuses them unless `allow_test` is set, and records the sha256 of the object list (`objects_sha256`) so that what
a dataset was built from can be checked later.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from ffcgs_jax.dataset.config import DatasetConfig
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.core.files import duplicate_stems
from ffcgs_jax.geometry import mesh_io, procedural

MESH_SUFFIXES = tuple(f".{s}" for s in mesh_io.FORMATS)
FAMILIES = {"procedural": procedural.shape, "complex": procedural.complex_shape}
"""Generated families: name -> (seed, index) -> (name, mesh)."""


@dataclass(frozen=True)
class Source:
    """One object of a build: name, split, category, the sha256 of its (scaled) geometry, the scale applied, and
    where its mesh comes from (a file, or a generated family's (seed, index)); `load` gives the scaled mesh."""

    name: str
    split: str
    category: str
    sha256: str
    scale: float = 1.0
    path: Path | None = None
    family: str = ""
    index: int = -1
    seed: int = 0

    def load(self) -> trimesh.Trimesh:
        if self.path is not None:
            mesh = mesh_io.load_mesh(self.path)
        else:
            mesh = FAMILIES[self.family](self.seed, self.index)[1]
        return scaled(mesh, self.scale)

    def describe(self) -> dict:
        """What the build's object list records of this object (and hashes)."""
        out = {"name": self.name, "split": self.split, "category": self.category, "mesh_sha256": self.sha256}
        if self.scale != 1.0:
            out["scale"] = self.scale
        return out


def scaled(mesh: trimesh.Trimesh, s: float) -> trimesh.Trimesh:
    return mesh if s == 1.0 else mesh.copy().apply_scale(s)


def object_seed(seed: int, name: str, *extra: int) -> int:
    """A 63-bit seed from the build seed, the object name and optional integers (rotation index, stream)."""
    text = ":".join(["ffcgs-dataset", str(seed), name, *map(str, extra)])
    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:8], "little") >> 1


def object_scale(cfg: DatasetConfig, name: str) -> float:
    """The object's scale factor: 1 when scale_min == scale_max == 1, else uniform in [scale_min, scale_max]."""
    if cfg.scale_min == cfg.scale_max:
        return float(cfg.scale_min)
    rng = np.random.default_rng(object_seed(cfg.seed, name, 0, 3))
    return float(rng.uniform(cfg.scale_min, cfg.scale_max))


def _categories(directory: Path) -> dict[str, str]:
    """file name -> category from an objects.json beside the meshes (the YCB set has one), else empty."""
    index = directory / "objects.json"
    if not index.is_file():
        return {}
    try:
        rows = json.loads(index.read_text()).get("objects", [])
        return {r["file"]: str(r.get("category", "")) for r in rows if isinstance(r, dict) and "file" in r}
    except (ValueError, AttributeError, TypeError):
        return {}  # the category is a label for summaries, not worth failing a build over


def _mesh_files(directory: Path) -> list[Path]:
    if directory.is_file():
        raise FfcgsError(f"objects directory {directory} is a file, not a folder")
    if not directory.is_dir():
        raise FfcgsError(f"objects directory not found: {directory}")
    found = sorted(p for p in directory.iterdir() if p.is_file() and p.suffix.lower() in MESH_SUFFIXES)
    if not found:
        raise FfcgsError(f"no mesh files ({', '.join(mesh_io.FORMATS)}) in {directory}")
    dup = duplicate_stems(found)
    if dup:
        raise FfcgsError(f"{directory}: several files share the name(s) {dup}; object names must be unique")
    return found


def _split_of(index: int) -> str:
    return "test" if index % 5 == 4 else "train"


def split_files(directory: str | Path, split: str) -> list[Path]:
    """The mesh files of `directory` in `split` ("train", "test" or "all"), in build order."""
    return [p for i, p in enumerate(_mesh_files(Path(directory))) if split in ("all", _split_of(i))]


def sources(cfg: DatasetConfig) -> list[Source]:
    """The objects of the build, in build order (module docstring). Refuses held-out objects unless
    `cfg.allow_test`; a mesh that does not load is named in one line before anything is built."""
    generated = cfg.procedural + cfg.complex
    if not cfg.objects and not generated:
        raise FfcgsError("--objects is required (a directory of meshes, e.g. shared/objects/ycb) unless the build "
                         "has generated shapes (--procedural N, --complex N)")
    if generated and cfg.split == "test":
        raise FfcgsError("generated shapes are training objects: --procedural and --complex need --split train "
                         "or all")
    if generated and cfg.seed in procedural.HELD_OUT_SEEDS and not cfg.allow_test:
        raise FfcgsError(f"seed {cfg.seed} generates a held-out set ({procedural.HELD_OUT_SEEDS[cfg.seed]}); "
                         f"choose another --seed, or pass --allow-test to build from it anyway")
    out: list[Source] = []
    stems: set[str] = set()
    if cfg.objects:
        directory = Path(cfg.objects)
        found = _mesh_files(directory)
        stems = {p.stem for p in found}
        cats = _categories(directory)
        for i, p in enumerate(found):
            split = _split_of(i)
            if cfg.split not in ("all", split):
                continue
            if split == "test" and not cfg.allow_test:
                raise FfcgsError(f"{p.name} is in the test split (sorted index {i}, i % 5 == 4), which is never "
                                 f"trained on; build --split train, or pass --allow-test to include it")
            s = object_scale(cfg, p.stem)
            # the geometry's identity, not the file's bytes: a re-saved or reformatted file is the same object
            mesh = scaled(mesh_io.load_mesh(p), s)
            out.append(Source(p.stem, split, cats.get(p.name, ""), mesh_io.mesh_sha256(mesh), s, path=p))
    if cfg.split in ("train", "all"):
        for family, count in (("procedural", cfg.procedural), ("complex", cfg.complex)):
            for i in range(count):
                name, mesh = FAMILIES[family](cfg.seed, i)
                if name in stems:
                    raise FfcgsError(f"{cfg.objects} has a file named like generated shape {name!r}; rename it or "
                                     f"build without --{family}")
                s = object_scale(cfg, name)
                out.append(Source(name, "train", family, mesh_io.mesh_sha256(scaled(mesh, s)), s, family=family,
                                  index=i, seed=cfg.seed))
    return out


def objects_sha256(srcs: list[Source]) -> str:
    """The sha256 of the object list: names, splits, categories, geometry hashes and scales, in build order."""
    text = json.dumps([s.describe() for s in srcs], sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def regenerate(name: str, config: dict) -> trimesh.Trimesh | None:
    """The mesh of generated object `name` of a dataset built with `config` (its stored build config), scaled as
    the build scaled it; None when `name` is not a generated shape."""
    prefixes = {"proc": "procedural", "cplx": "complex"}
    family = prefixes.get(name.split("_", 1)[0])
    if family is None:
        return None
    try:
        index = int(name.split("_")[1])
    except (IndexError, ValueError):
        return None
    cfg = stored_config(config)
    return scaled(FAMILIES[family](cfg.seed, index)[1], object_scale(cfg, name))


def stored_config(config: dict) -> DatasetConfig:
    """The fields of a stored build config that say which objects it built (seed and scales)."""
    return DatasetConfig(**{f: config[f] for f in ("seed", "scale_min", "scale_max") if f in config})
