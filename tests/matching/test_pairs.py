"""Pair selection: exhaustive, sequential and a pairs file, with one-line errors for bad specs and names."""


import pytest

from mvrecon.errors import InputError
from mvrecon.matching.pairs import select_pairs


def test_pair_selection(tmp_path):
    names = [f"f{i:02d}.jpg" for i in range(6)]
    assert len(select_pairs("exhaustive", names)) == 15
    seq = select_pairs("sequential:2", names)
    assert seq[:3] == [("f00.jpg", "f01.jpg"), ("f00.jpg", "f02.jpg"), ("f01.jpg", "f02.jpg")] and len(seq) == 9
    pairs_file = tmp_path / "pairs.txt"
    pairs_file.write_text("# my pairs\nf00.jpg f03.jpg\nf03.jpg f00.jpg\n\nf01.jpg f05.jpg  # comment\n")
    assert select_pairs(str(pairs_file), names) == [("f00.jpg", "f03.jpg"), ("f01.jpg", "f05.jpg")]
    pairs_file.write_text("f00.jpg f03.jpg\nf00.jpg nope.jpg\n")
    with pytest.raises(InputError, match=r"pairs.txt:2: unknown image 'nope.jpg'"):
        select_pairs(str(pairs_file), names)
    with pytest.raises(InputError, match="positive integer"):
        select_pairs("sequential:x", names)
