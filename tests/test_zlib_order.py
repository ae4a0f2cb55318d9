"""pycolmap's own zlib and the system's in one process (mvrecon/zlib_order.py): a process that imports mvrecon
before pycolmap writes PNGs and zlib data, and `mvrecon.cli.main` works even after pycolmap was imported first,
where a PNG written in the process itself aborts it (`free(): invalid pointer`). Each case runs in a fresh
interpreter, as the order of the first imports is what matters."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from PIL import Image

import mvrecon

ROOT = Path(mvrecon.__file__).resolve().parents[1]


def python(code: str, cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, (str(ROOT), os.environ.get("PYTHONPATH"))))}
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout)


def test_main_after_pycolmap_was_imported_first_makes_the_scene(tmp_path):
    # the lines exactly: this aborted in Pillow's PNG writer before the scene's images were written
    proc = python("import pycolmap; from mvrecon.cli import main; main(['scene','make','stereo_pair','-o','S'])",
                  tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "SIGABRT" not in proc.stderr
    assert "Import mvrecon (or zlib) before pycolmap" in proc.stderr  # the process is told why, and the cure
    for name in ("im0.png", "im1.png"):
        image = np.asarray(Image.open(tmp_path / "S" / "images" / name))
        assert image.shape[:2] == (768, 1024) and image.std() > 10  # a rendered view, not an empty file
    assert (tmp_path / "S" / "disp0GT.pfm").stat().st_size > 1024 * 768 * 4


def test_mvrecon_imported_first_keeps_pillow_and_zlib_whole(tmp_path):
    proc = python("import mvrecon, pycolmap, zlib; from PIL import Image; import numpy as np; "
                  "Image.fromarray(np.arange(81, dtype=np.uint8).reshape(9, 9)).save('x.png'); "
                  "data = bytes(range(256)) * 64; assert zlib.decompress(zlib.compress(data)) == data; "
                  "print(mvrecon.zlib_order.TAKEN_OVER)", tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split() == ["False"] and "RuntimeWarning" not in proc.stderr
    np.testing.assert_array_equal(np.asarray(Image.open(tmp_path / "x.png")), np.arange(81).reshape(9, 9))


def test_the_takeover_is_found_by_load_order(tmp_path):
    code = "import mvrecon.zlib_order as z; print(z.TAKEN_OVER)"
    taken = python("import pycolmap; " + code, tmp_path)
    assert taken.returncode == 0 and taken.stdout.split() == ["True"], taken.stderr[-2000:]
    assert "pycolmap was imported before mvrecon" in taken.stderr
    # libz.so.1 loaded first by anything (here Python's zlib module, as shutil does) leaves the process whole
    whole = python("import zlib, pycolmap; " + code, tmp_path)
    assert whole.returncode == 0 and whole.stdout.split() == ["False"] and "RuntimeWarning" not in whole.stderr
