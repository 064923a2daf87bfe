"""Voxel IoU metrics of imagined futures, accumulated over a held-out set.

Full-grid IoU = TP / (TP + FP + FN) over every voxel of the grid (not a query subset).

Dynamic IoU: the same ratio, counted only on the voxels where the true future or the
predicted future differs from the current frame (``V_t``): ``(V_{t+H} != V_t) | (P != V_t)``.
Static voxels that both truth and prediction keep as they are do not count, so a
prediction that copies the current frame (persistence) scores exactly 0, and a model only
scores by predicting the changes that happen. In mostly static scenes the full-grid figure
of persistence is high; the dynamic figure is the one that shows imagination.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch


def _counts(prediction: torch.Tensor, target: torch.Tensor, region: torch.Tensor | None = None) -> torch.Tensor:
    if region is not None:
        prediction, target = prediction & region, target & region
    true_positive = (prediction & target).sum()
    false_positive = (prediction & ~target).sum()
    false_negative = (~prediction & target).sum()
    return torch.stack([true_positive, false_positive, false_negative]).long()


def iou_from_counts(counts: torch.Tensor) -> float:
    """TP / (TP + FP + FN); 1.0 when both grids are empty (nothing to get wrong)."""
    true_positive, false_positive, false_negative = counts.tolist()
    union = true_positive + false_positive + false_negative
    return 1.0 if union == 0 else true_positive / union


def voxel_iou(prediction: torch.Tensor, target: torch.Tensor) -> float:
    """Full-grid IoU of two boolean occupancy grids of equal shape."""
    return iou_from_counts(_counts(prediction.bool(), target.bool()))


def dynamic_region(current: torch.Tensor, target: torch.Tensor, prediction: torch.Tensor) -> torch.Tensor:
    """Voxels where the true or the predicted future differs from the current frame."""
    return (target != current) | (prediction != current)


@dataclass
class IoUAccumulator:
    """Sums TP / FP / FN over many predictions, full grid and dynamic region.

    Example:
        >>> acc = IoUAccumulator()
        >>> acc.update(current, predicted, target)      # boolean (..., X, Y, Z) grids
        >>> acc.full_iou, acc.dynamic_iou
    """

    full: torch.Tensor = field(default_factory=lambda: torch.zeros(3, dtype=torch.long))
    dynamic: torch.Tensor = field(default_factory=lambda: torch.zeros(3, dtype=torch.long))

    def update(self, current: torch.Tensor, prediction: torch.Tensor, target: torch.Tensor) -> None:
        current, prediction, target = current.bool(), prediction.bool(), target.bool()
        self.full += _counts(prediction, target)
        self.dynamic += _counts(prediction, target, dynamic_region(current, target, prediction))

    @property
    def full_iou(self) -> float:
        return iou_from_counts(self.full)

    @property
    def dynamic_iou(self) -> float:
        return iou_from_counts(self.dynamic)
