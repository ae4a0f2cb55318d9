"""Ground-truth scenes: photo-textured meshes ray cast into images with exact cameras, poses, depth, points.

`list_scenes()` names the catalog entries (TOML files in the top-level `scenes/`); `make_scene(name, out_dir)`
renders one into a folder (deterministic and cached). See docs/scenes.md for the folder layout.
"""

from .catalog import list_scenes, make_scene

__all__ = ["list_scenes", "make_scene"]
