"""Opening the solid behind phantom surface, kept only where the likelihood prefers it.

The erosion of phantom surface (phantoms.py) sinks a lid one voxel at a time, and on the built-in cup it stalls: the
lid stood at 8-11 cm after 600 steps (the bottom is at 0.8 cm), and the data term was flat. Not because the data
cannot tell: with the cavity under that lid opened to the true shape, the deviance over all 256 views drops from
0.610 to 0.596 per bin, nearly all of it from the views above 60 degrees of elevation, which see the bottom. But a lid
a centimetre lower explains those views no better than this one; only the open cavity does. A gradient step cannot
get there, a jump can.

So every `schedule.open_every_steps` steps the model proposes jumps and keeps the best one that the likelihood
prefers:

1. The training steps of the last `open_passes` passes' worth of views before the round gather the same per-node
   evidence as the erosion: the log of measured over expected photons at each ray's return. Among the nodes at the
   surface as it is now (within a voxel of the zero level: the window also saw the surface where it was a few
   erosions ago), those with at least `phantom_min_hits` returns whose mean ratio is below `phantom_ratio` are
   *flagged* (phantom surface); those whose mean ratio is at least `open_keep_ratio` are *supported* (surface the
   data holds). With fewer than `open_min_flagged` flagged nodes the round makes no proposals and renders nothing.
2. For each depth D in `open_depths_m`: the solid within D of a flagged node and more than `open_keep_m` from every
   supported node (and from the floor, which the model counts as supported) is opened (`opened_field`): there the
   field becomes min(D - distance to the flagged nodes, distance to the supported ones - keep), a distance field of
   the opened region, where that is above the current value; only the pieces of that region that reach a flagged
   node open. The kept margin spares the walls the data
   holds, and the fine level then moves them to where the data puts them.
3. The current field and each proposal are rendered over all views with the same rays (common random numbers: the
   comparison does not see the sampling noise), and a proposal is kept if it lowers the deviance per bin by at least
   `open_min_gain`; the best such proposal wins. After `open_patience` rounds in a row without a kept proposal, the
   model stops proposing. A round with proposals costs about as much as 25 steps (one pass over all views per
   proposal and one for the current field); a round without them, nothing.

The minimum gain matters. The lids of the built-in cup and goblet gain 0.025-0.035 per bin. Where there is no phantom
surface, proposals gained at most 0.0013 per bin, and kept, they cut into the object: the top of the built-in lamp's
stem (0.0001-0.0002), 2 cm into the built-in sphere (0.0013).
"""

from __future__ import annotations

import numpy as np
import torch


def opening_distances(flagged: torch.Tensor, supported: torch.Tensor,
                      voxel: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(distance to the nearest flagged node, distance to the nearest supported node), metres, on the grid of the
    two (nz, ny, nx) bool masks (Euclidean distance transforms; inf where a mask is empty). Computed once per round
    of proposals: they do not depend on the depth."""
    from scipy.ndimage import distance_transform_edt

    if flagged.shape != supported.shape:
        raise ValueError(f"flagged {tuple(flagged.shape)} and supported {tuple(supported.shape)} must have one shape")
    if not voxel > 0:
        raise ValueError(f"voxel {voxel} m must be > 0")

    def distance(nodes: torch.Tensor) -> torch.Tensor:
        mask = nodes.detach().cpu().numpy()
        if not mask.any():  # no such node: infinitely far
            return torch.full(nodes.shape, float("inf"), device=nodes.device)
        return torch.from_numpy((distance_transform_edt(~mask) * voxel).astype(np.float32)).to(nodes.device)

    return distance(flagged), distance(supported)


def surface_classes(evidence, sdf: torch.Tensor, voxel: float, min_hits: int, low: float,
                    high: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(flagged, supported): `ReturnEvidence.classify(min_hits, low, high)` of `evidence`, restricted to the nodes
    within one voxel (metres) of the zero level of the SDF grid `sdf` (nz, ny, nx, metres, the evidence's grid). A
    round's evidence spans the steps before it, and some of its returns lay where the surface was, on a lid the
    erosion has sunk since. At the first round (step 150) on the built-in lamp, which has no phantom surface, 117
    nodes are flagged without this and 27 with it (three passes over all views under the current field flag 1); on
    the cup, whose lid is phantom surface, 1,140 and 492 (868)."""
    if tuple(sdf.shape) != evidence.shape:
        raise ValueError(f"grid {tuple(sdf.shape)} and evidence {evidence.shape} must have one shape")
    if not voxel > 0:
        raise ValueError(f"voxel {voxel} m must be > 0")
    flagged, supported = evidence.classify(min_hits, low, high)
    now = sdf.abs() <= voxel
    return flagged & now, supported & now


def opened_field(sdf: torch.Tensor, flagged: torch.Tensor, distances: tuple[torch.Tensor, torch.Tensor],
                 depth_m: float, keep_m: float) -> tuple[torch.Tensor, int]:
    """The SDF grid (nz, ny, nx, metres) with the solid behind flagged nodes opened (see the module).

    flagged: (nz, ny, nx) bool; distances: `opening_distances` of the flagged and supported nodes. Returns (new grid,
    number of nodes whose value rose). Inside the opened region (within `depth_m` of a flagged node, more than
    `keep_m` from a supported one, in a piece of that region that reaches a flagged node) the value becomes
    max(current, min(depth_m - d_flagged, d_supported - keep_m)); elsewhere it is unchanged. With no flagged nodes
    nothing changes.
    """
    from scipy.ndimage import label

    d_flagged, d_supported = distances
    if not (sdf.shape == flagged.shape == d_flagged.shape == d_supported.shape):
        raise ValueError(f"grid {tuple(sdf.shape)}, flagged {tuple(flagged.shape)} and distances must have one shape")
    if not (depth_m >= 0 and keep_m >= 0):
        raise ValueError(f"depth {depth_m} m and keep {keep_m} m must be >= 0")
    if not bool(flagged.any()):
        return sdf.clone(), 0
    value = torch.minimum(depth_m - d_flagged, d_supported - keep_m).to(sdf.dtype)
    # Only the pieces of the region that reach a flagged node: the opening grows from the phantom surface and never
    # jumps across the kept margin of a supported wall into the solid beyond it.
    pieces, _ = label((value > 0).cpu().numpy())
    reached = np.unique(pieces[flagged.cpu().numpy()])
    connected = torch.from_numpy(np.isin(pieces, reached[reached > 0])).to(sdf.device)
    rise = connected & (value > 0) & (sdf < value)
    return torch.where(rise, value, sdf), int(rise.sum())


__all__ = ["opened_field", "opening_distances", "surface_classes"]
