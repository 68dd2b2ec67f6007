"""The dataset subcommands: `ffcgs dataset build` (its options are `dataset.config.DatasetConfig`),
`ffcgs dataset info`, `ffcgs dataset export` and `ffcgs dataset merge`."""

import dataclasses
import json

import tyro

from ffcgs_jax.core import files
from ffcgs_jax.dataset.config import DatasetConfig
from ffcgs_jax.core.errors import FfcgsError


@dataclasses.dataclass(frozen=True)
class DatasetInfoCmd:
    """Print the counts and quality statistics of a dataset file; optionally draw its grasps.

    Attributes:
        dataset: the .mcap file `ffcgs dataset build` wrote.
        png: also draw a gallery per object into this directory (<object>.png: its first record's best grasps).
        objects: the mesh directory the dataset was built from (the file stores SDFs, not meshes); procedural
            shapes are regenerated without it.
        per_object: grasps drawn per object.
        json: also write the statistics to this JSON file.
        overwrite: replace the `--png` folder whole even when it holds files that no `dataset info` run wrote,
            or another command wrote it (its manifest says which).
    """

    dataset: tyro.conf.Positional[str] = tyro.MISSING
    png: str | None = None
    objects: str | None = None
    per_object: int = 4
    json: str | None = None
    overwrite: bool = False

    def check(self) -> None:
        if not 1 <= self.per_object <= 64:
            raise FfcgsError(f"--per-object must be in [1, 64], got {self.per_object}")


@dataclasses.dataclass(frozen=True)
class DatasetExportCmd:
    """Write a dataset file's records to numpy .npz, for use without MCAP.

    Attributes:
        dataset: the .mcap file `ffcgs dataset build` wrote.
        out: FILE.npz (the records stacked; grasp_start and grasp_record index each record's grasps) or a folder
            (one <record_id>.npz per record, replacing the folder whole). Fields: ffcgs_jax/dataset/export.py.
        overwrite: replace an `--out` folder whole even when it holds files that no `dataset export` run wrote,
            or another command wrote it (its manifest says which).
    """

    dataset: tyro.conf.Positional[str] = tyro.MISSING
    out: str = tyro.MISSING
    overwrite: bool = False


@dataclasses.dataclass(frozen=True)
class DatasetMergeCmd:
    """Write the dataset file from the parts that builds on one or many machines wrote into OUT.parts/ (a shared
    folder): every object's records must be there.

    Attributes:
        out: the .mcap file the builds were given as --out.
    """

    out: tyro.conf.Positional[str] = tyro.MISSING

    def check(self) -> None:
        if not self.out.endswith(".mcap"):
            raise FfcgsError(f"the dataset file must be an .mcap file, got {self.out!r}")


def run_dataset_merge(cmd: DatasetMergeCmd) -> None:
    from ffcgs_jax.dataset import build as dataset_build

    r = dataset_build.merge(cmd.out)
    files.announce(f"wrote {r['out']}: {r['records']} records of {r['objects']} objects")


def run_dataset_build(cfg: DatasetConfig) -> None:
    from ffcgs_jax.dataset import build as dataset_build

    r = dataset_build.build(cfg)
    done = (f"{r['built']} objects built ({r['engine']} engine), {r['skipped']} already done, {r['seconds']:.0f} s "
            f"(timing in {r['timing']})")
    if r.get("partial"):
        print(f"wrote {r['out']} with the annotated objects only: {done}; {r['missing']} records missing")
    elif r["out"] is None:
        print(f"shard {cfg.shard} finished: {done}; {r['missing']} records of other shards missing, so {cfg.out} "
              f"is not written yet (rerun without --shard once they are done)")
    else:
        print(f"wrote {r['out']}: {done}")


def run_dataset_info(cmd: DatasetInfoCmd) -> None:
    from ffcgs_jax.dataset import stats as dataset_stats

    stats = dataset_stats.stats(cmd.dataset)
    print(dataset_stats.format_stats(stats))
    if cmd.json:
        files.write_text(cmd.json, json.dumps(stats, indent=1))
        files.announce(f"wrote {cmd.json}")
    if cmd.png:
        from ffcgs_jax.viz import dataset_gallery

        with files.write_folder(cmd.png, "ffcgs dataset info") as tmp:
            written, skipped = dataset_gallery.gallery(cmd.dataset, tmp, cmd.per_object, cmd.objects)
        files.announce(f"wrote {len(written)} gallery picture(s) to {cmd.png}")
        if skipped:
            print(f"no picture for {len(skipped)} object(s) without grasps or mesh (pass --objects DIR): "
                  f"{', '.join(skipped[:8])}{' ...' if len(skipped) > 8 else ''}")


def run_dataset_export(cmd: DatasetExportCmd) -> None:
    from ffcgs_jax.dataset import export

    if cmd.out.lower().endswith(".npz"):
        r = export.export(cmd.dataset, cmd.out)
        where = cmd.out
    else:
        with files.write_folder(cmd.out, "ffcgs dataset export") as tmp:
            r = export.export(cmd.dataset, tmp)
        where = f"{len(r['files'])} files to {cmd.out}"
    files.announce(f"wrote {where}: {r['records']} records, {r['grasps']} grasps")
