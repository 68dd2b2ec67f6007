"""Which object a grasp file's grasps were planned on: shared by `ffcgs eval` and `ffcgs show`."""

from ffcgs_jax.core.errors import FfcgsError


def recorded_object(cmd, data: dict, builtins: list[str]) -> tuple[str, float]:
    """(object, scale) of the grasps in `data` (a grasp file's arrays): `cmd.object`/`cmd.scale` where given, else
    what the file records. `cmd` is any command with `grasps`, `object` and `scale` fields."""
    stored_scale = float(data["object_scale"]) if "object_scale" in data else None
    scale = cmd.scale if cmd.scale is not None else (stored_scale or 1.0)
    if cmd.object is not None:
        return cmd.object, scale
    if "object_source" in data:
        return str(data["object_source"]), scale
    stored = str(data.get("object_name", ""))  # files from before object_source was recorded
    if stored not in builtins:
        raise FfcgsError(f"{cmd.grasps} does not name a built-in object ({stored!r}): pass --object")
    return stored, scale


def not_the_recorded_object(name: str, scale: float, simulated: dict, data: dict) -> str:
    """The message for a mesh whose content hash (`simulated`, `mesh_io.identity`) is not the one grasp file `data`
    records: the same file (source and scale) whose content changed, or another object."""
    source = str(data.get("object_source", data.get("object_name", "?")))
    stored_scale = float(data["object_scale"]) if "object_scale" in data else 1.0
    same = source == str(simulated["object_source"]) and stored_scale == scale
    what = "its content changed since" if same else "the content differs"
    return (f"{name} (scale {scale:g}) is not the object these grasps were made for ({source}, scale "
            f"{stored_scale:g}): {what} (content hash {str(simulated['object_sha256'])[:12]}, the grasp file "
            f"records {str(data['object_sha256'])[:12]}); pass --other-object to simulate it anyway")
