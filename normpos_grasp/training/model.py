"""The bundled segmentation network (torch): a small YOLACT-style single-stage model.

Backbone of strided depthwise-separable blocks (RGB-D input) -> top-down feature pyramid -> (a) a prototype
branch at stride 4 producing `nm` prototype masks, (b) an anchor-free head at stride 8 predicting per cell a box
(distances to its four sides), class logits and `nm` mask coefficients. An instance mask is
sigmoid(coefficients . prototypes), as in YOLACT. `ExportWrapper` emits the YOLOv8-seg output layout that
`OnnxSegmenter` decodes: output0 (1, 4 + nc + nm, A) with boxes (cx, cy, w, h) in input pixels and sigmoid class
scores, output1 (1, nm, H/4, W/4).

torch is imported at module import: import this module only through the `train` extra.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F


def conv_bn(c_in: int, c_out: int, k: int = 3, s: int = 1, groups: int = 1, act: bool = True) -> nn.Sequential:
    layers: list[nn.Module] = [nn.Conv2d(c_in, c_out, k, s, k // 2, groups=groups, bias=False), nn.BatchNorm2d(c_out)]
    if act:
        layers.append(nn.ReLU(inplace=True))
    return nn.Sequential(*layers)


class DSBlock(nn.Module):
    """Residual depthwise-separable block: dw 3x3 -> pw 1x1 (expand) -> pw 1x1 (project)."""

    def __init__(self, c: int, expand: int = 2) -> None:
        super().__init__()
        self.body = nn.Sequential(
            conv_bn(c, c, 3, 1, groups=c), conv_bn(c, c * expand, 1), conv_bn(c * expand, c, 1, act=False)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(x + self.body(x))


def stage(c_in: int, c_out: int, blocks: int) -> nn.Sequential:
    return nn.Sequential(conv_bn(c_in, c_out, 3, 2), *[DSBlock(c_out) for _ in range(blocks)])


class SegNet(nn.Module):
    """Input (B, C, H, W), H and W multiples of 16. Returns (box (B, 4, h, w) as l, t, r, b in input pixels,
    class logits (B, nc, h, w), coefficients (B, nm, h, w), prototypes (B, nm, H/4, W/4)) with h, w = H/8, W/8."""

    stride = 8

    def __init__(self, in_channels: int = 4, num_classes: int = 8, num_protos: int = 32, width: int = 32) -> None:
        super().__init__()
        w = width
        self.nc, self.nm = num_classes, num_protos
        self.stem = stage(in_channels, w // 2, 0)  # /2
        self.s2 = stage(w // 2, w, 1)  # /4
        self.s3 = stage(w, 2 * w, 2)  # /8
        self.s4 = stage(2 * w, 3 * w, 2)  # /16
        self.s5 = stage(3 * w, 4 * w, 1)  # /32
        self.lat5 = conv_bn(4 * w, 2 * w, 1)
        self.lat4 = conv_bn(3 * w, 2 * w, 1)
        self.lat3 = conv_bn(2 * w, 2 * w, 1)
        self.lat2 = conv_bn(w, 2 * w, 1)
        self.smooth3 = nn.Sequential(conv_bn(2 * w, 2 * w, 3, groups=2 * w), conv_bn(2 * w, 2 * w, 1))
        self.proto = nn.Sequential(
            conv_bn(2 * w, 2 * w, 3, groups=2 * w), conv_bn(2 * w, 2 * w, 1), nn.Conv2d(2 * w, num_protos, 1)
        )
        self.head = nn.Sequential(conv_bn(2 * w, 2 * w, 3, groups=2 * w), conv_bn(2 * w, 3 * w, 1), DSBlock(3 * w))
        self.box = nn.Conv2d(3 * w, 4, 1)
        self.cls = nn.Conv2d(3 * w, num_classes, 1)
        self.coef = nn.Conv2d(3 * w, num_protos, 1)
        if self.cls.bias is not None:
            nn.init.constant_(self.cls.bias, -4.6)  # prior probability 0.01

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        c2 = self.s2(self.stem(x))
        c3 = self.s3(c2)
        c4 = self.s4(c3)
        c5 = self.s5(c4)
        p4 = self.lat4(c4) + F.interpolate(self.lat5(c5), size=c4.shape[-2:], mode="nearest")
        p3 = self.smooth3(self.lat3(c3) + F.interpolate(p4, size=c3.shape[-2:], mode="nearest"))
        p2 = self.lat2(c2) + F.interpolate(p3, size=c2.shape[-2:], mode="bilinear", align_corners=False)
        protos = self.proto(p2)
        h = self.head(p3)
        box = F.softplus(self.box(h)) * self.stride
        return box, self.cls(h), self.coef(h), protos


def anchor_centres(h: int, w: int, stride: int) -> torch.Tensor:
    """(h * w, 2) cell centres (x, y) in input pixels, row-major."""
    ys, xs = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    return torch.stack([(xs.reshape(-1) + 0.5) * stride, (ys.reshape(-1) + 0.5) * stride], dim=1).float()


class ExportWrapper(nn.Module):
    """SegNet -> (output0 (1, 4 + nc + nm, A), output1 (1, nm, H/4, W/4)) in the YOLOv8-seg layout."""

    def __init__(self, net: SegNet, input_hw: tuple[int, int]) -> None:
        super().__init__()
        self.net = net
        h, w = input_hw[0] // net.stride, input_hw[1] // net.stride
        self.register_buffer("centres", anchor_centres(h, w, net.stride).T.unsqueeze(0))  # (1, 2, A)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        box, cls, coef, protos = self.net(x)
        b = box.flatten(2)  # (1, 4, A) l, t, r, b
        c = self.get_buffer("centres")
        x1, y1 = c[:, 0:1] - b[:, 0:1], c[:, 1:2] - b[:, 1:2]
        x2, y2 = c[:, 0:1] + b[:, 2:3], c[:, 1:2] + b[:, 3:4]
        xywh = torch.cat([(x1 + x2) / 2, (y1 + y2) / 2, x2 - x1, y2 - y1], dim=1)
        out0 = torch.cat([xywh, torch.sigmoid(cls.flatten(2)), coef.flatten(2)], dim=1)
        return out0, protos
