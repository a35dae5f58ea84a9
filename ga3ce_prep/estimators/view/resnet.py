"""ResNet-50 (He et al. 2016) in torch, in torchvision's layout ("v1.5": the stride on the 3x3 conv
of each Bottleneck), so torchvision-style state dicts load into it by their key names:

    conv1, bn1, relu, maxpool, layer1 .. layer4 (3, 4, 6, 3 Bottlenecks), avgpool[, fc]
    layerN.i.{conv1, bn1, conv2, bn2, conv3, bn3}, layerN.0.downsample.{0 (1x1 conv), 1 (BN)}

With the 1000-way fc it has 25,557,032 parameters; `num_classes=None` leaves the fc out (the
2048-d pooled feature is the output, (N, 2048, 1, 1))."""
from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import nn

LAYERS = (3, 4, 6, 3)  # Bottlenecks per stage
WIDTHS = (64, 128, 256, 512)  # each stage's inner width; its output is 4x that


class Bottleneck(nn.Module):
    """1x1 (width) -> 3x3 (width, stride) -> 1x1 (4 width), batch-normed, plus the shortcut
    (a strided 1x1 conv + BN where the shape changes); ReLU after the sum."""

    expansion = 4

    def __init__(self, inplanes: int, width: int, stride: int = 1):
        super().__init__()
        out = width * self.expansion
        self.conv1 = nn.Conv2d(inplanes, width, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(width)
        self.conv2 = nn.Conv2d(width, width, 3, stride=stride, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(width)
        self.conv3 = nn.Conv2d(width, out, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(out)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = (nn.Sequential(nn.Conv2d(inplanes, out, 1, stride=stride, bias=False), nn.BatchNorm2d(out))
                           if stride != 1 or inplanes != out else None)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.relu(self.bn1(self.conv1(x)))
        y = self.relu(self.bn2(self.conv2(y)))
        y = self.bn3(self.conv3(y))
        return self.relu(y + (x if self.downsample is None else self.downsample(x)))


class ResNet50(nn.Module):
    """(N, 3, H, W) normalised image -> (N, num_classes) logits, or the pooled (N, 2048, 1, 1)
    feature when num_classes is None. Initialised as torchvision does (Kaiming-normal fan-out
    convs, BN weight 1 and bias 0)."""

    if TYPE_CHECKING:  # not at run time: TorchScript cannot read a string annotation
        layer1: nn.Sequential  # the four stages of Bottlenecks, set in __init__ (LAYERS, WIDTHS)
        layer2: nn.Sequential
        layer3: nn.Sequential
        layer4: nn.Sequential

    def __init__(self, num_classes: int | None = 1000):
        super().__init__()
        self.conv1 = nn.Conv2d(3, 64, 7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, stride=2, padding=1)
        inplanes = 64
        for i, (n, width) in enumerate(zip(LAYERS, WIDTHS)):
            blocks = [Bottleneck(inplanes, width, stride=1 if i == 0 else 2)]
            inplanes = width * Bottleneck.expansion
            blocks += [Bottleneck(inplanes, width) for _ in range(n - 1)]
            setattr(self, f"layer{i + 1}", nn.Sequential(*blocks))
        self.avgpool = nn.AdaptiveAvgPool2d(1)
        self.fc = nn.Linear(inplanes, num_classes) if num_classes is not None else None
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        x = self.avgpool(self.layer4(self.layer3(self.layer2(self.layer1(x)))))
        return x if self.fc is None else self.fc(torch.flatten(x, 1))


__all__ = ["Bottleneck", "ResNet50"]
