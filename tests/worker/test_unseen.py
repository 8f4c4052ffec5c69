"""Surface no ray reaches, relaxed on its air side (worker/recon/fast/parts/unseen.py)."""

from __future__ import annotations

import pytest
import torch

from spadscan.protocol.errors import ConfigError
from spadscan.worker.recon.fast.parts.unseen import UnseenConfig, UnseenRelaxation, relax_air_side, unseen_nodes

pytestmark = pytest.mark.usefixtures("one_thread")

VOXEL = 0.002


def underside(dent_nodes: float = 0.0, n: int = 24) -> torch.Tensor:
    """Distance (metres, (n, n, n), z first) of a solid above the plane z = 12.5 nodes, its underside pushed up by
    `dent_nodes` in a square 8 nodes across at the middle (a dent seen from below; the distance is the vertical one,
    which is what matters next to a near-flat underside)."""
    z = torch.arange(n, dtype=torch.float64)[:, None, None]
    h = torch.full((1, n, n), 12.5, dtype=torch.float64)
    h[:, 8:16, 8:16] += dent_nodes
    return ((h - z) * VOXEL).expand(n, n, n).clone()


def height_at(values: torch.Tensor, y: int, x: int) -> float:
    """Nodes: where the column (y, x) crosses zero, going up from air (positive) into solid (negative)."""
    col = values[:, y, x]
    k = int(torch.nonzero(col < 0)[0, 0])
    a, b = float(col[k - 1]), float(col[k])
    return k - 1 + a / (a - b)


def all_air_nodes(values: torch.Tensor, band_m: float) -> torch.Tensor:
    return unseen_nodes(values, torch.ones_like(values), band_m, 2.0)  # every air node in the band counts as unseen


def test_a_flat_unseen_surface_stays_where_it_is():
    values = underside(0.0)
    before = values.clone()
    nodes = all_air_nodes(values, 3 * VOXEL)
    assert nodes.numel() > 0
    relax_air_side(values, nodes, 50, 0.5)
    torch.testing.assert_close(values, before)


def test_an_unseen_dent_comes_down_and_the_solid_side_never_moves():
    values = underside(3.0)
    solid = values < 0
    before = values.clone()
    start = height_at(values, 12, 12)
    for _ in range(200):
        relax_air_side(values, all_air_nodes(values, 3 * VOXEL), 4, 0.5)
    # The dent's middle comes down, but only a little: what the solid side holds does not move, and the dent's
    # shape is in it (why the plant stand's unseen underside stays where an opening left it).
    assert start - 0.5 < height_at(values, 12, 12) < start - 0.05
    assert torch.equal(values[solid], before[solid])  # nothing already solid changed
    assert height_at(values, 2, 2) == pytest.approx(height_at(before, 2, 2), abs=0.01)  # the flat round it stays


def ball(radius_nodes: float, n: int = 16) -> torch.Tensor:
    """Distance (metres, (n, n, n)) of a solid ball at the grid's middle."""
    i = torch.arange(n, dtype=torch.float64) - (n - 1) / 2
    r = torch.sqrt(i[:, None, None] ** 2 + i[None, :, None] ** 2 + i[None, None, :] ** 2)
    return (r - radius_nodes) * VOXEL


def test_an_unseen_lump_shrinks_towards_its_solid_nodes():
    values = ball(2.6)
    before = values.clone()
    for _ in range(50):
        relax_air_side(values, all_air_nodes(values, 3 * VOXEL), 4, 0.5)
    solid = before < 0
    assert torch.equal(values[solid], before[solid])
    air = (before > 0) & (before < 3 * VOXEL)
    assert bool((values[air] >= before[air] - 1e-12).all()) and float((values - before)[air].max()) > 0.1 * VOXEL
    assert int((values < 0).sum()) == int(solid.sum())  # no air node turned solid: the lump only shrinks


def test_nodes_the_data_reaches_are_not_unseen():
    values = underside(3.0)
    seen = torch.zeros_like(values)
    seen[:, :, :12] = 1.0  # half of the grid has a data gradient
    nodes = unseen_nodes(values, seen, 3 * VOXEL, 0.01)
    n = values.shape[2]
    x = nodes % n
    assert nodes.numel() > 0 and bool((x >= 12).all())
    zyx = torch.stack([nodes // (n * n), (nodes // n) % n, x], dim=1)
    v = values[zyx[:, 0], zyx[:, 1], zyx[:, 2]]
    assert bool(((v > 0) & (v < 3 * VOXEL)).all())  # air side, within the band
    assert unseen_nodes(values, torch.zeros_like(values), 3 * VOXEL, 0.01).numel() == 0  # nothing seen: no reference


def test_relaxing_without_nodes_changes_nothing():
    values = underside(3.0)
    before = values.clone()
    relax_air_side(values, torch.zeros(0, dtype=torch.long), 4, 0.5)
    assert torch.equal(values, before)


@pytest.mark.parametrize("field, value", [("threshold", 0.0), ("threshold", 1.0), ("decay", 1.0), ("iterations", 0),
                                          ("alpha", 0.0), ("alpha", 1.5), ("band_voxels", 0.0),
                                          ("after_steps", -1), ("refresh_steps", 0)])
def test_bad_settings_are_refused_with_their_key(field, value):
    with pytest.raises(ConfigError, match=f"parts.unseen.{field}"):
        UnseenConfig(**{field: value}).check("parts.unseen")


class StandInField:
    def __init__(self, values: torch.Tensor):
        self.sdf, self.voxel = values[None, None], VOXEL


class StandInModel:
    """What the part reads of a model: the field, whether this is the last level, and the level's step count."""

    def __init__(self, values: torch.Tensor, level_steps: int):
        self.field, self.last_level, self.level_steps = StandInField(values), True, level_steps


def test_a_model_warm_started_late_in_its_last_level_waits_for_its_own_gradients():
    """A live refit starts a model at the last model's level and step count (800 here): the part relaxes nothing
    until `after_steps` gradients of its own are in its moving average, and then relaxes what none of them reached."""
    x = torch.arange(24, dtype=torch.float64)
    wall = ((x - 2.5) * VOXEL).expand(24, 24, 24)  # solid below x = 2.5 nodes
    values = torch.minimum(ball(2.6, n=24), wall).contiguous()
    model = StandInModel(values, level_steps=800)
    part = UnseenRelaxation(UnseenConfig(after_steps=5), model)
    grad = torch.zeros_like(values)[None, None]
    grad[0, 0, :, :, :5] = 1.0  # the data reaches the wall, not the ball
    before = values.clone()
    for k in range(5):
        part.after_gradient(model, grad)
        part.after_step(model, None)
        if k < 4:
            assert torch.equal(values, before), f"relaxed after {k + 1} gradient(s)"
    assert part.summary()["relaxed_nodes"] > 0 and not torch.equal(values, before)
    assert torch.equal(values[:, :, :5], before[:, :, :5])  # what the data reaches is left to it
    part.on_refine(model)  # a new level: the average starts again
    assert part.samples == 0 and part.seen is None
