"""Training targets of the world model: balanced voxel queries and the focal loss (eq. 4)."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def near_band(occupancy: torch.Tensor, distance: int) -> torch.Tensor:
    """Voxels within ``distance`` voxels (Chebyshev) of an occupied one, occupied ones included.

    ``occupancy`` is (B, X, Y, Z) bool; so is the result. A dilation by a cube is a dilation
    along each axis in turn, and along one axis it is the OR of the grid shifted by
    1 .. ``distance`` either way: boolean ORs of slices, no float max-pooling (at 128x128x32,
    distance 2-5: 15-25x faster than ``max_pool3d``, which took half a training step).
    """
    dilated = occupancy
    for dim in (1, 2, 3):
        source, dilated = dilated, dilated.clone()
        size = source.shape[dim]
        for shift in range(1, min(distance, size - 1) + 1):
            dilated.narrow(dim, shift, size - shift).logical_or_(source.narrow(dim, 0, size - shift))
            dilated.narrow(dim, 0, size - shift).logical_or_(source.narrow(dim, shift, size - shift))
    return dilated


def balanced_queries(
    target: torch.Tensor, n_queries: int, near_distance: int, generator: torch.Generator | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Voxel indices (B, Q, 3) and labels (B, Q) drawn in equal thirds from the occupied voxels,
    the free voxels within ``near_distance`` of the surface, and the far free voxels.

    A category that is empty in a sample gives its share to the others; draws are with
    replacement, so small categories may repeat.
    """
    batch, shape = target.shape[0], target.shape[1:]
    band = near_band(target, near_distance)
    categories = [target, band & ~target, ~band]
    indices, labels = [], []
    for b in range(batch):
        masks = [category[b].reshape(-1) for category in categories]
        present = [mask for mask in masks if mask.any()]
        shares = [n_queries // len(present) + (1 if i < n_queries % len(present) else 0) for i in range(len(present))]
        flat = torch.cat([
            torch.multinomial(mask.float(), share, replacement=True, generator=generator)
            for mask, share in zip(present, shares, strict=True)
        ])
        indices.append(torch.stack(torch.unravel_index(flat, shape), dim=-1))
        labels.append(target[b].reshape(-1)[flat].float())
    return torch.stack(indices), torch.stack(labels)


def focal_loss(
    logits: torch.Tensor, labels: torch.Tensor, alpha: float | None = 0.25, gamma: float = 2.0
) -> torch.Tensor:
    """Mean focal loss FL = -alpha_t (1 - p_t)^gamma log(p_t) (Lin et al., RetinaNet).

    p_t is the predicted probability of the true label; alpha_t = alpha for positives and
    1 - alpha for negatives (``alpha=None``: no class weighting). Computed from logits with
    the numerically stable binary cross-entropy, which equals -log(p_t).
    """
    cross_entropy = F.binary_cross_entropy_with_logits(logits, labels, reduction="none")
    probability = torch.sigmoid(logits)
    p_t = probability * labels + (1 - probability) * (1 - labels)
    loss = (1 - p_t) ** gamma * cross_entropy
    if alpha is not None:
        loss = (alpha * labels + (1 - alpha) * (1 - labels)) * loss
    return loss.mean()
