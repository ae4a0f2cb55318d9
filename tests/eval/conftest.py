"""The COLMAP runs that the comparison tests and the report's browser test share."""

import pytest

from mvrecon.eval.runners import RunOptions, run_colmap, run_colmap_on_database
from tests.helpers import shared_folder, synthetic_scene


@pytest.fixture(scope="session")
def colmap_runs(tmp_path_factory):
    """COLMAP end to end and COLMAP on that database, on helpers.synthetic_scene, once per test run:
    (images, ground truth, the COLMAP run, the run on COLMAP's database)."""
    with shared_folder(tmp_path_factory, "compare-shared") as root:  # each run is read back where it finished
        images, gt = synthetic_scene(root)
        options = RunOptions(camera_mode="single")  # test_compare's OPTS
        colmap = run_colmap(images, root / "runs" / "colmap", options)  # where compare_images(images, root) looks
        database = colmap.out_dir / "database.db"
        same = run_colmap_on_database(database, root / "colmap-on-colmap-db", images, options)
    return images, gt, colmap, same
