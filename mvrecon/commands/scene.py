"""Ground-truth scenes: list the catalog, or render one into a folder (images, COLMAP model, depth, extras).

mvrecon scene list                      names, kinds and descriptions of the catalog's scenes
mvrecon scene make NAME -o DIR          render scene NAME (or a path to a .toml) into DIR; cached,
                                        resumed after Ctrl-C
mvrecon scene make NAME -o DIR --count N    the same scene with N views (a larger survey, a longer street,
                                        a denser orbit)
"""

import argparse

from ..errors import InputError
from ..scenes import list_scenes, make_scene
from ..scenes.catalog import load_entry, read_scene_info

ORDER = 80
HOLDS_OUTPUT = True  # its -o folder is held against a second run (`io.files.hold_folder`)
ON_INTERRUPT = "the views rendered are kept; rerun the same command to continue"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("action", choices=("list", "make"), help="list the catalog, or make (render) a scene")
    parser.add_argument("name", nargs="?", help="make: a catalog name (`mvrecon scene list`) or a .toml path")
    parser.add_argument("-o", "--output",
                        help="make: output folder (created; reused when up to date, continued after Ctrl-C)")
    parser.add_argument("--count", type=int,
                        help="make: number of views instead of the scene's own (its trajectory stretches or "
                             "densifies: a larger survey, a longer street, a denser orbit)")


def run(args: argparse.Namespace) -> int:
    if args.action == "list":
        for name in list_scenes():
            entry = load_entry(name)[0]
            print(f"{name:22s} {entry.get('kind', 'perspective'):16s} {entry.get('description', '')}")
        return 0
    if not args.name or not args.output:
        raise InputError("scene make: give a scene NAME and an output folder with -o DIR")
    out = make_scene(args.name, args.output, count=args.count)
    info = read_scene_info(out)
    print(f"{out}: {info['name']} ({info['kind']}, {info.get('images', '?')} images, units: {info['units']})")
    return 0
