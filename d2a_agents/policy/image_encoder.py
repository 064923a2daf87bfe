"""The 2D Diffusion Policy's image encoder: ResNet-18 with GroupNorm, a spatial-softmax head.

As Diffusion Policy builds it (after robomimic): ResNet-18's convolutional trunk with every
BatchNorm replaced by GroupNorm (a group per 16 channels: small batches and EMA weights are
safe), no global pooling; a spatial softmax that turns K learned keypoint maps into their
expected image coordinates (2K numbers); a linear layer to the embedding. Images are cropped
to ``crop_fraction`` of their side, at a random place per image in training (the
augmentation) and in the centre otherwise. The stage widths are a setting: ResNet-18's
(64, 128, 256, 512) for the paper preset, a quarter of them on a CPU.

Example:
    >>> encoder = ImageEncoder(ImageEncoderConfig(widths=(16, 32, 64, 128)), out_dim=64)
    >>> encoder(torch.randint(0, 256, (8, 2, 84, 84, 3), dtype=torch.uint8)).shape
    torch.Size([8, 2, 64])
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

RESNET18_WIDTHS = (64, 128, 256, 512)
CHANNELS_PER_GROUP = 16
TRUNK_STRIDE = 32  # the trunk's five halvings: a side of n pixels leaves ceil(n / 32)


@dataclass(frozen=True)
class ImageEncoderConfig:
    """ResNet-18 stage widths, spatial-softmax keypoints and the crop (Diffusion Policy's defaults)."""

    widths: tuple[int, ...] = RESNET18_WIDTHS
    keypoints: int = 32
    crop_fraction: float = 0.9  # robomimic's 76 of 84 pixels

    def __post_init__(self) -> None:
        object.__setattr__(self, "widths", tuple(int(width) for width in self.widths))
        if len(self.widths) != 4 or min(self.widths) < 1:
            raise ValueError(f"a ResNet-18 has four stages of positive width, got {self.widths}")
        if self.keypoints < 1:
            raise ValueError(f"keypoints must be at least 1, not {self.keypoints}")
        if not 0 < self.crop_fraction <= 1:
            raise ValueError(f"crop_fraction must be in (0, 1], not {self.crop_fraction}")


def group_norm(channels: int) -> nn.GroupNorm:
    """GroupNorm with a group per 16 channels (one group below 16), as Diffusion Policy swaps BatchNorm."""
    return nn.GroupNorm(max(1, channels // CHANNELS_PER_GROUP), channels)


class BasicBlock(nn.Module):
    """ResNet's two 3x3 convolutions with a residual path (a strided 1x1 projection where the shape changes)."""

    def __init__(self, in_channels: int, out_channels: int, stride: int) -> None:
        super().__init__()
        self.body = nn.Sequential(
            nn.Conv2d(in_channels, out_channels, 3, stride, 1, bias=False), group_norm(out_channels),
            nn.ReLU(inplace=True),
            nn.Conv2d(out_channels, out_channels, 3, 1, 1, bias=False), group_norm(out_channels),
        )
        self.shortcut = nn.Identity() if stride == 1 and in_channels == out_channels else nn.Sequential(
            nn.Conv2d(in_channels, out_channels, 1, stride, bias=False), group_norm(out_channels))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.relu(self.body(x) + self.shortcut(x))


def resnet18_trunk(widths: tuple[int, ...]) -> nn.Sequential:
    """ResNet-18 up to its last convolution: a 7x7/2 stem, a 3x3/2 max-pool, four stages of two
    blocks (strides 1, 2, 2, 2); a 84-pixel image leaves as a 3x3 map of ``widths[-1]`` channels."""
    layers: list[nn.Module] = [nn.Conv2d(3, widths[0], 7, 2, 3, bias=False), group_norm(widths[0]),
                               nn.ReLU(inplace=True), nn.MaxPool2d(3, 2, 1)]
    in_channels = widths[0]
    for stage, width in enumerate(widths):
        stride = 1 if stage == 0 else 2
        layers += [BasicBlock(in_channels, width, stride), BasicBlock(width, width, 1)]
        in_channels = width
    return nn.Sequential(*layers)


class SpatialSoftmax(nn.Module):
    """(B, C, H, W) -> (B, 2K): K keypoint maps (a 1x1 convolution), each softmaxed over the
    pixels, and the expected (x, y) of each, pixel centres spanning [-1, 1] left to right and
    top to bottom."""

    def __init__(self, channels: int, keypoints: int) -> None:
        super().__init__()
        self.keypoint_maps = nn.Conv2d(channels, keypoints, 1)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        maps = self.keypoint_maps(features)
        batch, keypoints, height, width = maps.shape
        weights = torch.softmax(maps.reshape(batch, keypoints, height * width), dim=-1)
        ys, xs = torch.meshgrid(torch.linspace(-1, 1, height, device=maps.device),
                                torch.linspace(-1, 1, width, device=maps.device), indexing="ij")
        grid = torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=-1)  # (H * W, 2): x, y per pixel
        return (weights @ grid).reshape(batch, 2 * keypoints)


def crop_images(images: torch.Tensor, side: int, generator: torch.Generator | None = None,
                random: bool = True) -> torch.Tensor:
    """(N, H, W, C) -> (N, side, side, C): a random window per image, or the centre one."""
    count, height, width = images.shape[:3]
    if random:
        top = torch.randint(height - side + 1, (count,), generator=generator, device=images.device)
        left = torch.randint(width - side + 1, (count,), generator=generator, device=images.device)
    else:
        top = torch.full((count,), (height - side) // 2, device=images.device)
        left = torch.full((count,), (width - side) // 2, device=images.device)
    offsets = torch.arange(side, device=images.device)
    rows, cols = (top[:, None] + offsets)[:, :, None], (left[:, None] + offsets)[:, None, :]
    return images[torch.arange(count, device=images.device)[:, None, None], rows, cols]


class ImageEncoder(nn.Module):
    """(..., H, W, 3) colour images (uint8, or floats in [0, 255]) -> (..., out_dim) features."""

    def __init__(self, config: ImageEncoderConfig, out_dim: int) -> None:
        super().__init__()
        self.config = config
        self.trunk = resnet18_trunk(config.widths)
        self.keypoints = SpatialSoftmax(config.widths[-1], config.keypoints)
        self.project = nn.Linear(2 * config.keypoints, out_dim)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        leading, (height, width) = images.shape[:-3], images.shape[-3:-1]
        flat = images.reshape(-1, height, width, images.shape[-1])
        side = round(self.config.crop_fraction * min(height, width))
        if side <= TRUNK_STRIDE:
            raise ValueError(f"a {side}-pixel crop leaves the ResNet-18 trunk a 1x1 map, where the spatial softmax "
                             f"sees no position: use images whose crop exceeds {TRUNK_STRIDE} pixels")
        cropped = crop_images(flat, side, random=self.training)
        pixels = cropped.permute(0, 3, 1, 2).float() / 127.5 - 1.0  # [0, 255] -> [-1, 1], channels first
        return self.project(self.keypoints(self.trunk(pixels))).reshape(*leading, -1)
