"""Config machinery: the config hash (workers do not change it), TOML overrides, diffs, unknown options."""


import pytest

from mvrecon import config as cfgmod
from mvrecon.errors import InputError
from mvrecon.stages.common import FrontendConfig


def test_config_hash_overrides_and_diff(tmp_path):
    base = FrontendConfig()
    assert cfgmod.config_hash(base) == cfgmod.config_hash(FrontendConfig(workers=7))  # workers do not change results
    toml = tmp_path / "c.toml"
    toml.write_text('pairs = "sequential:3"\n[sift]\nmax_num_features = 1000\n')
    changed = cfgmod.with_overrides(base, cfgmod.load_toml(toml), source=str(toml))
    assert changed.sift.max_num_features == 1000 and changed.pairs == "sequential:3"
    assert cfgmod.config_hash(changed) != cfgmod.config_hash(base)
    assert cfgmod.diff(cfgmod.to_dict(base), cfgmod.to_dict(changed)) == [
        "pairs: auto -> sequential:3", "sift.max_num_features: 8192 -> 1000"]
    toml.write_text("[sift]\nmax_features = 1\n")
    with pytest.raises(InputError, match="unknown option 'max_features' in SiftConfig"):
        cfgmod.with_overrides(base, cfgmod.load_toml(toml), source=str(toml))
