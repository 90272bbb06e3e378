"""The double U-Net of paper III-B-b, sized for a 2-core CPU.

U-Net 1: depth crop (2 x S x S: normalised depth, validity) -> 15-class body-part logits.
U-Net 2: depth + softmax(segmentation) (17 x S x S) -> 3 normalised canonical coordinates.
The 6-D pixel embedding is (coordinates, colour of the predicted part); paper Eq. 2 maps it
to a template vertex (body.parts.EmbeddingIndex).

`SingleUNet` (correspondence only, no segmentation prior) is the ablation of hypothesis
H1: one U-Net predicting the 15 logits and the 3 coordinates from depth alone.
"""
from __future__ import annotations

import torch
from torch import nn
import torch.nn.functional as F

from smpl_depth_ros.body.parts import NUM_CLASSES

INPUT_SIZE = 128  # network input: S x S crop around the person
IN_CHANNELS = 2   # normalised depth, validity mask (see net.preprocess)


def _block(cin, cout):
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True))


class UNet(nn.Module):
    """A compact U-Net: `depth` down-sampling levels, channel widths `widths`."""

    def __init__(self, cin: int, cout: int, widths=(16, 32, 48, 64)):
        super().__init__()
        self.down = nn.ModuleList()
        c = cin
        for w in widths:
            self.down.append(_block(c, w))
            c = w
        self.up = nn.ModuleList()
        self.upconv = nn.ModuleList()
        for w in reversed(widths[:-1]):
            self.upconv.append(nn.Conv2d(c, w, 1))
            self.up.append(_block(2 * w, w))
            c = w
        self.head = nn.Conv2d(c, cout, 1)

    def forward(self, x):
        skips = []
        for i, blk in enumerate(self.down):
            x = blk(x)
            if i < len(self.down) - 1:
                skips.append(x)
                x = F.max_pool2d(x, 2)
        for upc, blk in zip(self.upconv, self.up):
            s = skips.pop()
            x = F.interpolate(upc(x), size=s.shape[-2:], mode='bilinear', align_corners=False)
            x = blk(torch.cat([x, s], 1))
        return self.head(x)


class DoubleUNet(nn.Module):
    """Segmentation U-Net followed by the coordinate U-Net (paper Fig. 1).

    forward(depth (B,2,S,S)) -> (logits (B,15,S,S), coords (B,3,S,S) in [0,1]).
    """

    kind = 'double'

    def __init__(self, seg_widths=(16, 32, 64, 96), corr_widths=(12, 24, 40, 56)):
        super().__init__()
        # Segmentation needs context (left/right is decided by the whole silhouette), so
        # U-Net 1 is the wider one; U-Net 2 refines coordinates given the parts.
        self.seg = UNet(IN_CHANNELS, NUM_CLASSES, seg_widths)
        self.corr = UNet(IN_CHANNELS + NUM_CLASSES, 3, corr_widths)

    def forward(self, depth):
        logits = self.seg(depth)
        # Stop-gradient: U-Net 1 learns from the segmentation loss alone. Letting the
        # coordinate loss flow back through the softmax cost 0.2-0.3 mIoU in our runs.
        coords = torch.sigmoid(self.corr(torch.cat([depth, logits.detach().softmax(1)], 1)))
        return logits, coords


class SingleUNet(nn.Module):
    """Ablation: one U-Net, both outputs from depth alone (no segmentation input)."""

    kind = 'single'

    def __init__(self, widths=(20, 40, 64, 88)):
        super().__init__()
        self.net = UNet(IN_CHANNELS, NUM_CLASSES + 3, widths)

    def forward(self, depth):
        out = self.net(depth)
        return out[:, :NUM_CLASSES], torch.sigmoid(out[:, NUM_CLASSES:])


def build_network(kind: str = 'double', widths=None) -> nn.Module:
    if kind == 'double':
        return DoubleUNet(*widths) if widths else DoubleUNet()
    if kind == 'single':
        return SingleUNet(tuple(widths) if widths else (20, 40, 64, 88))
    raise ValueError(f'unknown network kind {kind!r}')
