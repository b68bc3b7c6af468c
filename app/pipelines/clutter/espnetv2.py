"""ESPNetv2 (Mehta et al., CVPR 2019), width s = 2.0, as a Cityscapes segmentation network.

The clutter paper segments each camera image to find people and vehicles. We use the published
Cityscapes weights (`espnetv2_s_2.0_city_1024x512.pth`, see `/work/shared/models/README.md`):
small (3.4 MB), about half a second per KITTI frame on one CPU thread. This module is written
from the layer-by-layer description in `ESPNETV2.md`; its parameter names and shapes are those
of the state dict, so the weights load with `strict=True`.

Encoder (`base_net`): CBR stride 2 -> DownSampler x3 (with input reinforcement) and stacks of
EESP blocks, channels 32 / 128 / 256 / 512 at 1/2 .. 1/16 resolution. Decoder: EfficientPyrPool
at each level, joined to the encoder features by EfficientPWConv, bilinear upsampling x2, and a
last bilinear resize to the input size. Output: 20 class scores per pixel (CITYSCAPES_CLASSES).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F  # noqa: N812 (torch convention)
from torch import nn

CITYSCAPES_CLASSES = (
    "road",
    "sidewalk",
    "building",
    "wall",
    "fence",
    "pole",
    "traffic light",
    "traffic sign",
    "vegetation",
    "terrain",
    "sky",
    "person",
    "rider",
    "car",
    "truck",
    "bus",
    "train",
    "motorcycle",
    "bicycle",
    "background",
)

ENCODER_CHANNELS = (32, 128, 256, 512)  # s = 2.0
DECODER_PLANES = (64, 48, 32, len(CITYSCAPES_CLASSES))
PYRAMID_PROJECTION = 10
PYRAMID_SCALES = (2.0, 1.5, 1.0, 0.5, 0.1)
KERNEL_TO_DILATION = {3: 1, 5: 2, 7: 3, 9: 4, 11: 5, 13: 6, 15: 7, 17: 8}


def _up_to(x: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """Bilinear x2 upsampling (align_corners=True) onto the skip feature's grid; with sizes
    divisible by 16 this is exactly x2, otherwise it absorbs the off-by-one."""
    return F.interpolate(x, like.shape[-2:], mode="bilinear", align_corners=True)


class CBR(nn.Module):
    """Conv -> BatchNorm -> PReLU: the basic unit of the encoder."""

    def __init__(self, nin: int, nout: int, k: int, stride: int = 1, groups: int = 1):
        super().__init__()
        self.conv = nn.Conv2d(nin, nout, k, stride, (k - 1) // 2, bias=False, groups=groups)
        self.bn = nn.BatchNorm2d(nout)
        self.act = nn.PReLU(nout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.bn(self.conv(x)))


class CB(nn.Module):
    """Conv -> BatchNorm, no activation: used before a residual sum."""

    def __init__(self, nin: int, nout: int, k: int, stride: int = 1, groups: int = 1):
        super().__init__()
        self.conv = nn.Conv2d(nin, nout, k, stride, (k - 1) // 2, bias=False, groups=groups)
        self.bn = nn.BatchNorm2d(nout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.bn(self.conv(x))


class BR(nn.Module):
    """BatchNorm -> PReLU (encoder naming: `.bn`, `.act`)."""

    def __init__(self, n: int):
        super().__init__()
        self.bn = nn.BatchNorm2d(n)
        self.act = nn.PReLU(n)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.bn(x))


class CDilated(nn.Module):
    """Depth-wise dilated 3x3 conv: one EESP branch, receptive field set by the dilation."""

    def __init__(self, n: int, stride: int, dilation: int):
        super().__init__()
        self.conv = nn.Conv2d(n, n, 3, stride, dilation, dilation=dilation, bias=False, groups=n)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(x)


def _cbr_seq(nin: int, nout: int, k: int, groups: int = 1) -> nn.Sequential:
    """Decoder CBR, stored as a Sequential (children 0, 1, 2) as in the state dict."""
    return nn.Sequential(
        nn.Conv2d(nin, nout, k, 1, (k - 1) // 2, bias=False, groups=groups),
        nn.BatchNorm2d(nout),
        nn.PReLU(nout),
    )


def _br_seq(n: int) -> nn.Sequential:
    """Decoder BatchNorm -> PReLU as a Sequential (children 0, 1)."""
    return nn.Sequential(nn.BatchNorm2d(n), nn.PReLU(n))


class DecoderCBR(nn.Module):
    """CBR whose layers sit under `.cbr` (decoder naming)."""

    def __init__(self, nin: int, nout: int, k: int, groups: int = 1):
        super().__init__()
        self.cbr = _cbr_seq(nin, nout, k, groups)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.cbr(x)


class DecoderBR(nn.Module):
    """BR whose layers sit under `.br` (decoder naming)."""

    def __init__(self, n: int):
        super().__init__()
        self.br = _br_seq(n)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.br(x)


class EESP(nn.Module):
    """Extremely Efficient Spatial Pyramid: grouped 1x1 reduce, k depth-wise dilated branches
    fused hierarchically (removes gridding artefacts), grouped 1x1 expand, residual."""

    def __init__(self, nin: int, nout: int, stride: int = 1, k: int = 4, r_lim: int = 7):
        super().__init__()
        self.stride = stride
        n = nout // k
        if n * k != nout:
            raise ValueError(f"EESP: nout={nout} is not divisible by k={k}")
        self.proj_1x1 = CBR(nin, n, 1, groups=k)
        k_sizes = sorted(3 + 2 * i if 3 + 2 * i <= r_lim else 3 for i in range(k))
        self.spp_dw = nn.ModuleList(CDilated(n, stride, KERNEL_TO_DILATION[s]) for s in k_sizes)
        self.conv_1x1_exp = CB(nout, nout, 1, groups=k)
        self.br_after_cat = BR(nout)
        self.module_act = nn.PReLU(nout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        reduced = self.proj_1x1(x)
        outs = [self.spp_dw[0](reduced)]
        for branch in self.spp_dw[1:]:
            outs.append(branch(reduced) + outs[-1])
        expanded = self.conv_1x1_exp(self.br_after_cat(torch.cat(outs, 1)))
        if self.stride == 2:  # inside a DownSampler: its caller concatenates and activates
            return expanded
        if expanded.shape == x.shape:
            expanded = expanded + x
        return self.module_act(expanded)


class DownSampler(nn.Module):
    """Strided EESP beside an average pool, plus input reinforcement: the image itself,
    pooled to this resolution, is added back so that deep levels keep the raw colours."""

    def __init__(self, nin: int, nout: int, k: int = 4, r_lim: int = 9):
        super().__init__()
        self.eesp = EESP(nin, nout - nin, stride=2, k=k, r_lim=r_lim)
        self.avg = nn.AvgPool2d(3, stride=2, padding=1)
        self.inp_reinf = nn.Sequential(CBR(3, 3, 3), CB(3, nout, 1))
        self.act = nn.PReLU(nout)

    def forward(self, x: torch.Tensor, image: torch.Tensor | None = None) -> torch.Tensor:
        pooled = self.avg(x)
        out = torch.cat([pooled, self.eesp(x)], 1)
        if image is not None:
            while image.shape[-1] > pooled.shape[-1]:
                image = F.avg_pool2d(image, 3, stride=2, padding=1)
            out = out + self.inp_reinf(image)
        return self.act(out)


class EESPNetEncoder(nn.Module):
    """The ImageNet backbone up to level 4 (level 5 and the classifier are not in the weights)."""

    def __init__(self, channels: tuple[int, int, int, int] = ENCODER_CHANNELS):
        super().__init__()
        c1, c2, c3, c4 = channels
        self.level1 = CBR(3, c1, 3, stride=2)
        self.level2_0 = DownSampler(c1, c2, r_lim=13)
        self.level3_0 = DownSampler(c2, c3, r_lim=11)
        self.level3 = nn.ModuleList(EESP(c3, c3, r_lim=9) for _ in range(3))
        self.level4_0 = DownSampler(c3, c4, r_lim=9)
        self.level4 = nn.ModuleList(EESP(c4, c4, r_lim=7) for _ in range(7))

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Features at 1/2, 1/4, 1/8, 1/16 (the decoder joins all four)."""
        l1 = self.level1(image)
        l2 = self.level2_0(l1, image)
        l3 = self.level3_0(l2, image)
        for block in self.level3:
            l3 = block(l3)
        l4 = self.level4_0(l3, image)
        for block in self.level4:
            l4 = block(l4)
        return l1, l2, l3, l4


class Shuffle(nn.Module):
    """Channel shuffle: interleave the pyramid levels so the grouped conv after it mixes them."""

    def __init__(self, groups: int):
        super().__init__()
        self.groups = groups

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        x = x.view(b, self.groups, c // self.groups, h, w).transpose(1, 2)
        return x.reshape(b, c, h, w)


class EfficientPyrPool(nn.Module):
    """Decoder block: project to few channels, depth-wise conv at five scales (x2 .. x0.1) for
    context at almost no cost, merge the scales with a shuffle and a grouped conv."""

    def __init__(self, in_planes: int, proj_planes: int, out_planes: int, last_layer_br=True):
        super().__init__()
        self.scales = PYRAMID_SCALES
        self.projection_layer = DecoderCBR(in_planes, proj_planes, 1)
        self.stages = nn.ModuleList(
            nn.Conv2d(proj_planes, proj_planes, 3, 1, 1, bias=False, groups=proj_planes)
            for _ in self.scales
        )
        n = len(self.scales)
        self.merge_layer = nn.Sequential(
            DecoderBR(n * proj_planes),
            Shuffle(n),
            DecoderCBR(n * proj_planes, proj_planes, 3, groups=proj_planes),
            nn.Conv2d(proj_planes, out_planes, 1, bias=not last_layer_br),
        )
        self.br = DecoderBR(out_planes) if last_layer_br else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.projection_layer(x)
        h, w = x.shape[-2:]
        levels = []
        for scale, stage in zip(self.scales, self.stages, strict=True):
            hs, ws = max(math.ceil(h * scale), 5), max(math.ceil(w * scale), 5)
            if scale < 1.0:
                y = stage(F.adaptive_avg_pool2d(x, (hs, ws)))
                y = F.interpolate(y, (h, w), mode="bilinear", align_corners=True)
            elif scale > 1.0:
                y = stage(F.interpolate(x, (hs, ws), mode="bilinear", align_corners=True))
                y = F.adaptive_avg_pool2d(y, (h, w))
            else:
                y = stage(x)
            levels.append(y)
        out = self.merge_layer(torch.cat(levels, 1))
        return out if self.br is None else self.br(out)


class EfficientPWConv(nn.Module):
    """Encoder-to-decoder join: grouped 3x3 CBR re-weighted per channel by a sigmoid of the
    global average (squeeze-excitation-like), cheaper than a full point-wise conv."""

    def __init__(self, nin: int, nout: int):
        super().__init__()
        self.wt_layer = nn.Sequential(
            nn.AdaptiveAvgPool2d(1), nn.Conv2d(nin, nout, 1, bias=False), nn.Sigmoid()
        )
        self.expansion_layer = DecoderCBR(nin, nout, 3, groups=math.gcd(nin, nout))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.expansion_layer(x) * self.wt_layer(x)


class ESPNetv2Seg(nn.Module):
    """ESPNetv2 segmentation: (B, 3, H, W) ImageNet-normalised RGB -> (B, 20, H, W) scores.

    H and W divisible by 16 keep the encoder and decoder resolutions aligned.
    """

    def __init__(self, num_classes: int = len(CITYSCAPES_CLASSES)):
        super().__init__()
        c1, c2, c3, c4 = ENCODER_CHANNELS
        p1, p2, p3, _ = DECODER_PLANES
        proj = PYRAMID_PROJECTION
        self.base_net = EESPNetEncoder()
        self.bu_dec_l1 = EfficientPyrPool(c4, proj, p1)
        self.bu_dec_l2 = EfficientPyrPool(p1, proj, p2)
        self.bu_dec_l3 = EfficientPyrPool(p2, proj, p3)
        self.bu_dec_l4 = EfficientPyrPool(p3, proj, num_classes, last_layer_br=False)
        self.merge_enc_dec_l2 = EfficientPWConv(c3, p1)
        self.merge_enc_dec_l3 = EfficientPWConv(c2, p2)
        self.merge_enc_dec_l4 = EfficientPWConv(c1, p3)
        self.bu_br_l2 = _br_seq(p1)
        self.bu_br_l3 = _br_seq(p2)
        self.bu_br_l4 = _br_seq(p3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        l1, l2, l3, l4 = self.base_net(x)
        d = self.bu_dec_l1(l4)
        d = self.bu_dec_l2(self.bu_br_l2(_up_to(d, l3) + self.merge_enc_dec_l2(l3)))
        d = self.bu_dec_l3(self.bu_br_l3(_up_to(d, l2) + self.merge_enc_dec_l3(l2)))
        d = self.bu_dec_l4(self.bu_br_l4(_up_to(d, l1) + self.merge_enc_dec_l4(l1)))
        return F.interpolate(d, x.shape[-2:], mode="bilinear", align_corners=True)
