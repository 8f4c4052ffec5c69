"""The plateau test's window is what docs/fast_method.md says: max(10, patience_steps / 6) steps, rounded down."""

from __future__ import annotations

from pathlib import Path

import pytest

from spadscan.worker.recon.fast.parts.plateau import Plateau

DOC = Path(__file__).resolve().parents[2] / "docs" / "fast_method.md"


@pytest.mark.parametrize("patience, window", [(30, 10), (60, 10), (65, 10), (66, 11), (600, 100), (1000, 166)])
def test_the_window_is_a_sixth_of_the_patience_and_never_under_10_steps(patience, window):
    assert Plateau(patience, 1e-3).window == window


def test_a_patience_of_30_steps_needs_at_least_40_steps_of_a_flat_loss():
    plateau = Plateau(30, 1e-3)
    reached = [plateau.update(1.0) for _ in range(60)]
    assert reached.index(True) + 1 == 40


def test_the_doc_gives_the_window_as_the_code_computes_it():
    text = " ".join(DOC.read_text().split())
    assert "windows of max(10, `parts.plateau.patience_steps` / 6) steps (rounded down" in text
    assert "windows of `parts.plateau.patience_steps` / 6 steps" not in text
