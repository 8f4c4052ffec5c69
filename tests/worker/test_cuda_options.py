"""The CUDA tests' config overrides are current, checked where no GPU is: the CUDA tests themselves skip there (CI
never runs them), so an override renamed since would otherwise fail only on a GPU."""

from __future__ import annotations

import pytest

from spadscan.protocol.errors import SpadscanError
from spadscan.worker.recon.config import with_overrides
from spadscan.worker.recon.presets import preset_config
from worker_helpers import CUDA_CLI_SMALL, CUDA_SMALL, PAPER_SMALL


@pytest.mark.parametrize("preset, overrides",
                         [("fast", CUDA_SMALL), ("fast", CUDA_CLI_SMALL), ("paper", PAPER_SMALL)],
                         ids=["fast", "fast-command-line", "paper"])
def test_every_override_of_the_cuda_tests_names_a_current_config_key(preset, overrides):
    config = with_overrides(preset_config(preset), overrides)
    for key, value in overrides.items():
        node = config
        for part in key.split("."):
            node = getattr(node, part)
        assert (list(node) if isinstance(node, tuple) else node) == value, key


@pytest.mark.parametrize("key", ["field.refine_after_steps", "field.no_such_key"])
def test_a_renamed_or_unknown_key_is_refused_so_the_check_above_can_fail(key):
    with pytest.raises(SpadscanError, match=key):
        with_overrides(preset_config("fast"), {key: 60})
