"""The 3D CNN of the paper (Fig. 4): LeNet-style, three 3x3x3 convolutions with ReLU, two
2x2x2 max-pools, dropout 0.5 then 0.25, two fully connected layers, softmax over the four
pillar classes {ground, high object, short object, phantom}.

Input: a pillar's 11 x 11 pillar neighbourhood, 22 x 22 x 30 voxels of point counts (log1p).
The paper zero-pads the border so that the first convolution keeps 22 x 22 x 30. We keep that
size but give the first convolution one voxel of real *context* around the window in x and y
(the window is cut 24 x 24 from the map) and zero padding only in z, where the column ends
anyway. This is what makes the dense (fully-convolutional) evaluation of `dense_logits`
*exactly* equal to the per-window network: with zeros at every window border, overlapping
windows could not share their convolutions.

Tensor layout: (batch, C, z, x, y): C = 1 point counts, or C = 2 with `passes` (beyond the paper:
time as evidence, pillars.py), the distinct scanner passes per voxel beside the counts; both read
as log1p.

Beyond the paper, optional (`context` > 0 channels): a 2.2 m window cannot tell the middle of a
parked car from the middle of a car smeared along the road, or a parked car from an oncoming one
compressed to half its length; both need the object's extent. A second, 2D branch reads the
pillar's `CONTEXT_SPAN` x `CONTEXT_SPAN` pillar surroundings (6.2 m) as counts per pillar and
0.5 m height band, through four 3 x 3 convolutions dilated 1, 2, 4, 8 (stride 1, no padding:
exactly one output per pillar, so the dense path is the same convolutions over a larger block),
and its features join the first fully connected layer.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F  # noqa: N812 (torch convention)
from torch import nn

from app.core.labels import PILLAR_CLASS_NAMES

CLASS_NAMES = PILLAR_CLASS_NAMES  # the network's outputs, in pillar class order
COUNT_CLIP = 255.0  # voxel counts saturate here (training windows are stored as uint8)
CONTEXT_BANDS = 6  # height bands of the context branch: 0.5 m each over the 3 m pillar
CONTEXT_DILATIONS = (1, 2, 4, 8)
CONTEXT_SPAN = 1 + 2 * sum(CONTEXT_DILATIONS)  # 31 pillars: the context branch's field of view


def _counts(x: torch.Tensor) -> torch.Tensor:
    return torch.log1p(torch.clamp(x, max=COUNT_CLIP))


class ContextNet(nn.Module):
    """The context branch: (N, 6, 31 + T - 1, 31 + T - 1) pillar band counts -> (N, C, T, T)."""

    def __init__(self, channels: int = 16):
        super().__init__()
        sizes = [CONTEXT_BANDS] + [channels] * len(CONTEXT_DILATIONS)
        self.convs = nn.ModuleList(
            nn.Conv2d(a, b, 3, dilation=d)
            for a, b, d in zip(sizes[:-1], sizes[1:], CONTEXT_DILATIONS, strict=True)
        )

    def forward(self, bands: torch.Tensor) -> torch.Tensor:
        x = _counts(bands)
        for conv in self.convs:
            x = F.relu(conv(x))
        return x


class PillarCNN(nn.Module):
    def __init__(
        self,
        channels: tuple[int, int, int] = (8, 16, 32),
        hidden: int = 64,
        height: int = 30,
        window: int = 22,
        classes: int = 4,
        context: int = 0,
        passes: bool = False,
    ):
        super().__init__()
        c1, c2, c3 = channels
        self.channels, self.hidden, self.height, self.window = channels, hidden, height, window
        self.context = context  # channels of the context branch, 0 = the paper's network
        self.passes = passes  # reads distinct scanner passes per voxel beside the counts
        self.conv1 = nn.Conv3d(2 if passes else 1, c1, 3, padding=(1, 0, 0))
        self.pool1 = nn.MaxPool3d(2)
        self.conv2 = nn.Conv3d(c1, c2, 3)
        self.pool2 = nn.MaxPool3d(2)
        self.drop1 = nn.Dropout(0.5)
        self.conv3 = nn.Conv3d(c2, c3, 3)
        self.drop2 = nn.Dropout(0.25)
        z, xy = self.conv3_shape(height, window)
        self.fine_features = c3 * z * xy * xy
        self.context_net = ContextNet(context) if context else None
        self.fc1 = nn.Linear(self.fine_features + context, hidden)
        self.fc2 = nn.Linear(hidden, classes)

    @staticmethod
    def conv3_shape(height: int, window: int) -> tuple[int, int]:
        """(z, xy) size after conv3 for a window of `window` voxels (+2 context) and `height`."""
        z = ((height // 2) - 2) // 2 - 2
        xy = ((window // 2) - 2) // 2 - 2
        return z, xy

    def features(self, x: torch.Tensor) -> torch.Tensor:
        x = _counts(x)
        x = self.pool1(F.relu(self.conv1(x)))
        x = self.pool2(F.relu(self.conv2(x)))
        return F.relu(self.conv3(self.drop1(x)))

    def forward(self, x: torch.Tensor, bands: torch.Tensor | None = None) -> torch.Tensor:
        """Logits (N, 4) of windows (N, C, 30, 24, 24) and, with a context branch, their
        surroundings (N, 6, 31, 31)."""
        x = self.drop2(self.features(x)).flatten(1)
        if self.context_net is not None:
            if bands is None:
                raise ValueError("this network has a context branch: pass the band counts")
            x = torch.cat([x, self.context_net(bands).flatten(1)], dim=1)
        return self.fc2(F.relu(self.fc1(x)))

    def config(self) -> dict:
        return {
            "channels": list(self.channels),
            "hidden": self.hidden,
            "height": self.height,
            "window": self.window,
            "context": self.context,
            "passes": self.passes,
        }


@torch.no_grad()
def dense_logits(
    net: PillarCNN, block: torch.Tensor, bands: torch.Tensor | None = None
) -> torch.Tensor:
    """The network evaluated at every pillar of a block at once (shared convolutions).

    `block` (1, C, 30, 2T + 22, 2T + 22) voxels starting one context voxel before pillar P0's
    window; returns logits (4, T, T) whose [:, u, v] is the per-window output of the window whose
    first pillar is P0 + (u, v), i.e. of the pillar P0 + (u, v) + 5. The second max-pool loses
    its stride (windows one pillar apart are not aligned with it), so later layers dilate by 2.
    With a context branch, `bands` (1, 6, T + 30, T + 30) are the band counts from pillar
    P0 + 5 - 15 on, and T is the smaller of the two sizes.
    """
    x = _counts(block)
    x = F.max_pool3d(F.relu(net.conv1(x)), 2)
    x = F.relu(net.conv2(x))
    x = F.max_pool3d(x, kernel_size=2, stride=(2, 1, 1))
    x = F.relu(F.conv3d(x, net.conv3.weight, net.conv3.bias, dilation=(1, 2, 2)))
    z, xy = net.conv3_shape(net.height, net.window)
    c3 = net.channels[2]
    w1 = net.fc1.weight[:, : net.fine_features].reshape(net.hidden, c3, z, xy, xy)
    x = F.conv3d(x, w1, net.fc1.bias, dilation=(1, 2, 2))[0, :, 0]  # (hidden, t, t)
    t = (block.shape[-1] - net.window) // 2
    if net.context_net is not None:
        if bands is None:
            raise ValueError("this network has a context branch: pass the band counts")
        context = net.context_net(bands)[0]  # (C, t', t')
        t = min(t, context.shape[-1])
        w_context = net.fc1.weight[:, net.fine_features :]
        x = x[:, :t, :t] + torch.einsum("hc,cuv->huv", w_context, context[:, :t, :t])
    x = F.relu(x[:, :t, :t])
    return torch.einsum("kh,huv->kuv", net.fc2.weight, x) + net.fc2.bias[:, None, None]
